"""Where training log records go: JSONL (always), TensorBoard, Weights & Biases.

The training loop (:func:`dispgns.training.train`) does no I/O: it hands every log record to its
``on_log`` callable. A record is a flat mapping with ``"kind"`` (``"train"`` or ``"validation"``),
``"step"`` and numbers (see :func:`~dispgns.training.loop.train`). A logger here is such a callable
with a ``close()``; :class:`LoggerGroup` fans one record out to several. Write your own as any
``callable(record)``; pass it as ``on_log=``.

Non-finite numbers never reach a JSON file: :func:`json_safe` turns them into ``null`` (JSON has no
NaN; Python's ``json`` would write the non-standard token ``NaN``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "LOGGERS",
    "LoggerGroup",
    "TensorBoardLogger",
    "WandbLogger",
    "json_safe",
    "make_logger",
]

LOGGERS = ("jsonl", "tensorboard", "wandb")
TENSORBOARD_DIR = "tensorboard"


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float (also inside lists, dicts, numpy values) replaced by ``None``."""
    if isinstance(value, Mapping):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (np.ndarray, np.generic)) or type(value).__module__.startswith("jax"):
        return json_safe(np.asarray(value).tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _scalars(record: Mapping[str, Any]) -> dict[str, float]:
    """The record's numbers (not ``kind``/``step``) under ``kind/name`` tags."""
    kind = record.get("kind", "log")
    out = {}
    for name, value in record.items():
        if name in ("kind", "step") or isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
            continue
        out[f"{kind}/{name}"] = float(value)
    return out


class TensorBoardLogger:
    """Scalars for TensorBoard through ``tensorboardX`` (``pip install 'dispgns[tensorboard]'``).

    Each number of a record becomes the scalar ``kind/name`` at ``step`` (e.g. ``train/loss``,
    ``validation/valid_rollout_mse``), written under ``log_dir`` (``RUN/tensorboard`` from the CLI);
    ``tensorboard --logdir RUN/tensorboard`` shows them.
    """

    def __init__(self, log_dir: str | os.PathLike, config: Mapping[str, Any] | None = None):
        try:
            from tensorboardX import SummaryWriter
        except ModuleNotFoundError:
            raise ModuleNotFoundError(
                "--logger tensorboard needs tensorboardX: pip install 'dispgns[tensorboard]'"
            ) from None
        self.log_dir = Path(log_dir)
        self._writer = SummaryWriter(logdir=str(self.log_dir))
        if config:
            import json

            self._writer.add_text("config", "```\n" + json.dumps(json_safe(config), indent=2) + "\n```", 0)

    def __call__(self, record: Mapping[str, Any]) -> None:
        step = int(record.get("step", 0))
        for tag, value in _scalars(record).items():
            self._writer.add_scalar(tag, value, step)

    def close(self) -> None:
        self._writer.flush()
        self._writer.close()


class WandbLogger:
    """A Weights & Biases run through ``wandb`` (``pip install 'dispgns[wandb]'``).

    Args:
      run_dir: the training run directory (``wandb`` keeps its files in ``run_dir/wandb``).
      config: logged as the run's config.
      project: the W&B project (default ``dispgns``).
      mode: ``"offline"`` (default: no network; ``wandb sync`` uploads later), ``"online"`` or
        ``"disabled"``; ``None`` takes ``WANDB_MODE`` from the environment, else offline.
      name: the run's name (default: the run directory's name).
    """

    def __init__(
        self,
        run_dir: str | os.PathLike,
        config: Mapping[str, Any] | None = None,
        *,
        project: str = "dispgns",
        mode: str | None = None,
        name: str | None = None,
    ):
        try:
            import wandb
        except ModuleNotFoundError:
            raise ModuleNotFoundError("--logger wandb needs wandb: pip install 'dispgns[wandb]'") from None
        mode = mode or os.environ.get("WANDB_MODE") or "offline"
        run_dir = Path(run_dir)
        self._run = wandb.init(
            project=project,
            dir=str(run_dir),
            config=json_safe(dict(config or {})),
            mode=mode,
            name=name or run_dir.name,
            reinit=True,
        )
        self.directory = Path(self._run.dir).parent if self._run is not None else None

    def __call__(self, record: Mapping[str, Any]) -> None:
        values = {tag: value for tag, value in _scalars(record).items() if math.isfinite(value)}
        self._run.log(values, step=int(record.get("step", 0)))

    def close(self) -> None:
        self._run.finish()


class LoggerGroup:
    """Several loggers as one ``on_log`` callable; ``close()`` closes them all (each even if one fails)."""

    def __init__(self, loggers: Sequence[Callable[[Mapping[str, Any]], None]]):
        self.loggers = list(loggers)

    def __call__(self, record: Mapping[str, Any]) -> None:
        for logger in self.loggers:
            logger(record)

    def close(self) -> None:
        errors = []
        for logger in self.loggers:
            close = getattr(logger, "close", None)
            if close is not None:
                try:
                    close()
                except Exception as error:  # close the others first, then report
                    errors.append(error)
        if errors:
            raise errors[0]


def make_logger(
    kind: str, run_dir: str | os.PathLike, config: Mapping[str, Any] | None = None, **options: Any
) -> TensorBoardLogger | WandbLogger:
    """The logger ``kind`` (``"tensorboard"`` or ``"wandb"``) for a run directory; ``options`` go to it."""
    if kind == "tensorboard":
        return TensorBoardLogger(Path(run_dir) / TENSORBOARD_DIR, config)
    if kind == "wandb":
        return WandbLogger(run_dir, config, **options)
    raise ValueError(f"unknown logger {kind!r}, expected one of {list(LOGGERS[1:])} (jsonl is always on)")
