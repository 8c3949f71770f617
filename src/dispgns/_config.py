"""The one config validator: frozen config dataclasses from plain mappings, and their field checks.

Every config (``PhysicsConfig``, ``ModelConfig``, ``TrainConfig``, ...) is a
frozen dataclass; :func:`config_from_mapping` builds one from JSON, YAML or
command-line text, and :func:`check_fields` validates its fields in
``__post_init__`` with messages that name the class, the field, the
expected value and what was given.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from typing import Any

__all__ = ["check_fields", "config_from_mapping"]


def _is_integer(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and float(value).is_integer()


def _is_number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def check_fields(
    config,
    *,
    integers: Mapping[str, int] = {},
    positive: Iterable[str] = (),
    nonnegative: Iterable[str] = (),
    choices: Mapping[str, Iterable[Any]] = {},
) -> None:
    """Validate fields of a config dataclass; a ``ValueError`` names the class, field, expectation and value.

    Args:
      config: the config instance (in its ``__post_init__``).
      integers: field -> minimum, for integer fields.
      positive, nonnegative: finite-number fields that must be > 0 or >= 0.
      choices: field -> allowed values.
    """
    owner = type(config).__name__

    def fail(name, expected):
        raise ValueError(f"{owner}.{name} must be {expected}, got {getattr(config, name)!r}")

    for name, minimum in integers.items():
        value = getattr(config, name)
        if not _is_integer(value) or value < minimum:
            fail(name, f"an integer >= {minimum}")
    for name in positive:
        value = getattr(config, name)
        if not (_is_number(value) and value > 0):
            fail(name, "a finite number > 0")
    for name in nonnegative:
        value = getattr(config, name)
        if not (_is_number(value) and value >= 0):
            fail(name, "a finite number >= 0")
    for name, allowed in choices.items():
        allowed = list(allowed)
        if getattr(config, name) not in allowed:
            fail(name, f"one of {allowed}")


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
        expected = "a boolean" if kind is bool else "an integer" if kind is int else "a number"
        raise ValueError(f"{owner}.{name} must be {expected}, got {text!r}") from None
