"""The renderer's float32 boundary under mixed precision (``torch.autocast``).

Under autocast a matmul or a convolution runs in bfloat16 or float16, whose 8 or 11 significant bits cannot hold
the depth tests, the barycentrics near a face's edge or the occupancy ``exp(-d / sigma)`` with ``sigma = 1e-4``.
The renderer therefore runs with autocast disabled and its 16-bit floating inputs cast to float32: its images are
what a float32 run makes from the same inputs. float32 and float64 inputs are left as they are.
"""

from __future__ import annotations

import contextlib
from typing import overload

import torch

__all__ = ["autocast_active", "full_precision", "to_full_precision"]

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
