"""The renderer's float32 boundary under mixed precision (``torch.autocast``).

Under autocast a matmul or a convolution runs in bfloat16 or float16, whose 8 or 11 significant bits cannot hold
the depth tests, the barycentrics near a face's edge or the occupancy ``exp(-d / sigma)`` with ``sigma = 1e-4``.
The renderer therefore runs with autocast disabled and its 16-bit floating inputs cast to float32: its images are
what a float32 run makes from the same inputs. float32 and float64 inputs are left as they are.
:func:`float32_boundary` puts a renderer's entry point behind that boundary.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar, overload

import torch

__all__ = ["autocast_active", "float32_boundary", "full_precision", "to_full_precision"]

_P = ParamSpec("_P")
_R = TypeVar("_R")

_REDUCED = (torch.float16, torch.bfloat16)


def autocast_active(device_type: str) -> bool:
    """Whether autocast is enabled for ``device_type`` (``"cpu"``, ``"cuda"``...) in this thread."""
    return torch.amp.is_autocast_available(device_type) and torch.is_autocast_enabled(device_type)


def full_precision(device_type: str) -> contextlib.AbstractContextManager[None]:
    """A context in which autocast is off for ``device_type``; a no-op context when it is off already."""
    if autocast_active(device_type):
        return torch.autocast(device_type=device_type, enabled=False)
    return contextlib.nullcontext()


@overload
def to_full_precision(tensor: torch.Tensor) -> torch.Tensor: ...
@overload
def to_full_precision(tensor: None) -> None: ...
def to_full_precision(tensor: torch.Tensor | None) -> torch.Tensor | None:
    """``tensor`` in float32 when it is float16 or bfloat16, else unchanged (None stays None)."""
    if tensor is not None and tensor.dtype in _REDUCED:
        return tensor.float()
    return tensor


def _cast(value: Any) -> Any:
    """A 16-bit floating tensor in float32, textures (anything with ``full_precision()``) in float32; else as is."""
    if isinstance(value, torch.Tensor):
        return to_full_precision(value)
    if callable(getattr(value, "full_precision", None)):
        return value.full_precision()
    return value


def _device_type(args: tuple[Any, ...], kwargs: dict[str, Any]) -> str:
    """The device type of the first tensor among the arguments after ``self``, positional then keyword
    (``"cpu"`` without one)."""
    for value in (*args[1:], *kwargs.values()):
        if isinstance(value, torch.Tensor):
            return value.device.type
    return "cpu"


def float32_boundary(method: Callable[_P, _R]) -> Callable[_P, _R]:
    """Run ``method(self, verts, ...)`` in float32 under autocast: with autocast off for the device of its tensor
    arguments (the first one's, passed by position or by keyword), and its float16 and bfloat16 tensor arguments
    and its textures cast to float32 first. Without autocast the call is unchanged."""

    @functools.wraps(method)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        device_type = _device_type(args, kwargs)
        if not autocast_active(device_type):
            return method(*args, **kwargs)
        args = tuple(_cast(a) for a in args)  # type: ignore[assignment]
        kwargs = {k: _cast(v) for k, v in kwargs.items()}  # type: ignore[assignment]
        with torch.autocast(device_type=device_type, enabled=False):
            return method(*args, **kwargs)

    return wrapper
