"""Building frozen config dataclasses from plain mappings (JSON, YAML, command-line overrides)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any


def config_from_mapping(cls, values: Mapping[str, Any]):
    """``cls(**values)`` with unknown keys refused and numbers given as text converted.

    YAML 1.1 reads ``1e-3`` (no dot) as a string, and command-line overrides
    are text: a string given for a field whose default is a float, an int or
    a bool is converted, and a clear error names the field when it cannot be.
    """
    if not isinstance(values, Mapping):
        raise ValueError(f"{cls.__name__} needs a mapping of field: value, got {type(values).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ValueError(f"unknown {cls.__name__} field(s) {unknown}; expected a subset of {sorted(fields)}")
    converted = {}
    for name, value in values.items():
        default = fields[name].default
        if isinstance(value, str) and isinstance(default, (bool, int, float)) and default is not None:
            value = _parse(cls.__name__, name, value, type(default))
        elif isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        converted[name] = value
    return cls(**converted)


def _parse(owner: str, name: str, text: str, kind: type):
    try:
        if kind is bool:
            lowered = text.strip().lower()
            if lowered in ("true", "yes", "on", "1"):
                return True
            if lowered in ("false", "no", "off", "0"):
                return False
            raise ValueError(text)
        if kind is int:
            number = float(text)
            if number != int(number):
                raise ValueError(text)
            return int(number)
        return float(text)
    except ValueError:
        raise ValueError(
            f"{owner}.{name} must be {'a boolean' if kind is bool else f'an {kind.__name__}' if kind is int else 'a number'}, "
            f"got {text!r}"
        ) from None
