"""Progressive conditioning: fixed-size codes of which only the first ``active_dims`` values are used.

The paper grows the shape, texture and background latent spaces stage by stage (e.g. 0/2/8/64 for the
shape code). Codes keep their full size; a mask zeroes the trailing dimensions. The active count is a
buffer, so it is saved with the model and can be changed at run time by the training schedule.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["ProgressiveMask", "active_dims_at"]


def active_dims_at(step: float, powers: Sequence[int], milestones: Sequence[float]) -> int:
    """Code size in force at ``step``: the largest power whose milestone is <= step, 0 before the first.

    Args:
        step: current epoch or iteration (same unit as ``milestones``).
        powers: increasing code sizes, e.g. ``[2, 8, 32]``.
        milestones: when each power starts, e.g. ``[m1, m2, m3]`` (same length as ``powers``).

    Example:
        >>> active_dims_at(5, [2, 8, 32], [3, 10, 20])
        2
        >>> active_dims_at(0, [2, 8, 32], [3, 10, 20])
        0
    """
    if len(powers) != len(milestones):
        raise ValueError(f"powers and milestones differ in length: {len(powers)} vs {len(milestones)}")
    dims = 0
    for power, milestone in zip(powers, milestones, strict=True):
        if step >= milestone:
            dims = int(power)
    return dims


class ProgressiveMask(nn.Module):
    """Keeps the first ``active_dims`` entries of a ``(B, code_dim)`` code and zeroes the rest.

    Args:
        code_dim: full code size (the regressor's output size, never changes).
        active_dims: initial number of active dimensions (0 to ``code_dim``).
    """

    active: torch.Tensor

    def __init__(self, code_dim: int, active_dims: int | None = None) -> None:
        super().__init__()
        if code_dim < 0:
            raise ValueError(f"code_dim must be >= 0, got {code_dim}")
        self.code_dim = int(code_dim)
        self._active_host: int | None = None
        self.register_buffer("active", torch.tensor(code_dim if active_dims is None else 0, dtype=torch.long))
        if active_dims is not None:
            self.set_active_dims(active_dims)

    @property
    def active_dims(self) -> int:
        """Number of code dimensions currently used."""
        # a host copy of the buffer: reading a CUDA buffer at every step would synchronise with the device
        if self._active_host is None:
            self._active_host = int(self.active)
        return self._active_host

    def set_active_dims(self, n: int) -> None:
        """Use the first ``n`` dimensions from now on (0 means a code that is all zeros)."""
        if isinstance(n, bool) or not float(n).is_integer() or not 0 <= n <= self.code_dim:  # 2.5 is no count
            raise ValueError(f"active dims must be a whole number in [0, {self.code_dim}], got {n!r}")
        n = int(n)
        self.active.fill_(n)
        self._active_host = n

    def _load_from_state_dict(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        super()._load_from_state_dict(*args, **kwargs)
        self._active_host = None  # the buffer may have changed: read it again when asked

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """(B, code_dim) -> (B, code_dim) with the trailing ``code_dim - active_dims`` entries set to 0."""
        if code.shape[-1] != self.code_dim:
            raise ValueError(f"code must have {self.code_dim} values in its last dim, got {tuple(code.shape)}")
        keep = torch.arange(self.code_dim, device=code.device) < self.active.to(code.device)
        return code * keep.to(code.dtype)

    def extra_repr(self) -> str:
        return f"code_dim={self.code_dim}, active_dims={self.active_dims}"
