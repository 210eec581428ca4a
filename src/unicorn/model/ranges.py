"""Dataclass fields with a range: declared with :func:`ranged`, checked by :func:`check_ranges`.

The model's configuration (:mod:`unicorn.model.config`), the training schema and the evaluation and diagnostics
settings declare their numeric ranges this way, so that each range is written once, next to its default.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import field
from typing import Any

from unicorn.errors import UserError

__all__ = ["ModelConfigError", "check_ranges", "describe_range", "field_range", "ranged"]


class ModelConfigError(UserError, ValueError):
    """A model configuration value out of its range, not among the allowed ones, or not fitting another value
    (the message names the key)."""


def ranged(default: Any, low: float | None = None, high: float | None = None) -> Any:
    """A dataclass field whose value must lie in ``[low, high]`` (either bound may be None), checked by
    :func:`check_ranges`. ``None`` values (optional fields) are not checked."""
    return field(default=default, metadata={"range": (low, high)})


def _dataclass_of(hint: Any) -> type | None:
    """The dataclass in a type hint (``X`` or ``X | None``), or None."""
    if dataclasses.is_dataclass(hint):
        return hint  # type: ignore[return-value]
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        return next((a for a in typing.get_args(hint) if dataclasses.is_dataclass(a)), None)
    return None


def field_range(schema: type, name: str) -> tuple[float | None, float | None]:
    """The ``[low, high]`` range of a :func:`ranged` field (``(None, None)``: unchecked). A subclass that only
    changes a field's default keeps the range its base class declares."""
    for cls in schema.__mro__:
        f = getattr(cls, "__dataclass_fields__", {}).get(name)
        if f is not None and "range" in f.metadata:
            return f.metadata["range"]
    return None, None


def describe_range(low: float | None, high: float | None) -> str:
    """``">= 1"``, ``"<= 5"`` or ``"in [0, 1]"``."""
    if high is None:
        return f">= {low:g}"
    if low is None:
        return f"<= {high:g}"
    return f"in [{low:g}, {high:g}]"


def check_ranges(values: Mapping[str, Any], schema: type, prefix: str = "") -> None:
    """Check every field of ``schema`` declared with :func:`ranged`, recursing into nested groups: a finite number
    within its bounds, a whole number where the field is an ``int`` (a size or a count: ``64.5`` is refused, not
    rounded; ``64.0`` passes).

    Raises:
        ModelConfigError: the first value out of its range (or not finite, or not whole), named with its full key
            (``prefix`` + path).
    """
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        value = values.get(f.name)
        key = f"{prefix}{f.name}"
        nested = _dataclass_of(hints[f.name])
        if nested is not None:
            if value is not None:
                check_ranges(value, nested, f"{key}.")
            continue
        low, high = field_range(schema, f.name)
        if value is None or (low is None and high is None):
            continue
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or (isinstance(value, float) and not math.isfinite(value)):  # an int is finite (10**400 too)
            raise ModelConfigError(f"{key} must be a finite number {describe_range(low, high)}, got {value!r}")
        if hints[f.name] is int and isinstance(value, float) and not value.is_integer():
            raise ModelConfigError(f"{key} must be a whole number {describe_range(low, high)}, got {value!r}")
        if not ((low is None or value >= low) and (high is None or value <= high)):
            raise ModelConfigError(f"{key} must be {describe_range(low, high)}, got {value}")
