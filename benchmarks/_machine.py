"""The machine a benchmark ran on, for its JSON report: one helper shared by the scripts in ``benchmarks/``.

Imported as ``from _machine import ...``: a script run as ``python benchmarks/NAME.py`` has this directory on
``sys.path``. Standard library only, so importing it starts nothing (no JAX backend before the allocator tuning).
"""

from __future__ import annotations

import os
import platform
from typing import Any

__all__ = ["cpu_model", "machine_info"]


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (Linux), else what :mod:`platform` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(**extra: Any) -> dict[str, Any]:
    """``{"cpu", "cores", "load_average_1min"}``, then ``extra`` (a script's own fields: versions, settings).

    The load average is read when this is called: call it when the measurement ends, so the report says
    how busy the machine was while it ran.
    """
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "load_average_1min": os.getloadavg()[0], **extra}
