"""Separable image filters as two small matrix products, the border padding folded into the matrices.

On the CPU, oneDNN runs the depthwise convolutions of one to three channels that image filters usually become
(kornia's filters, a ``groups=C`` conv) several times slower than these products, forward and backward; on
CUDA they are one batched GEMM. Used by the structural perceptual loss (SSIM, Sobel) and the generators' blur.

The matrices are built once per size and filter and cached. A graph ``torch.compile`` traces asks the cache through
one operator (``unicorn::filter_matrix``, a copy of the cached matrix) instead of rebuilding the matrix with a
dozen small operations in every graph that filters.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from unicorn.caching import cache_outside_compile

__all__ = ["filter_matrix", "separable_filter"]


def filter_matrix(n: int, taps: list[float], mode: str, like: torch.Tensor) -> torch.Tensor:
    """(n, n) matrix M with ``(v @ M)[j] = sum_t taps[t] * pad(v)[j + t]`` for length-n vectors v.

    ``pad`` adds ``len(taps) // 2`` values on each side in ``mode`` (``"reflect"`` or ``"replicate"``, torch's
    padding modes); padding is linear, so it is folded into the matrix by padding the identity. Built on
    ``like``'s device and dtype (no host-device copy) once per size, taps, mode, dtype and device: the result
    is shared, do not modify it in place.
    """
    if len(taps) % 2 == 0:
        raise ValueError(f"need an odd number of taps, got {len(taps)}")
    if torch.compiler.is_compiling():
        return _cached_filter_matrix(n, [float(t) for t in taps], mode, like.dtype, like.device)
    return _filter_matrix(n, tuple(float(t) for t in taps), mode, like.dtype, like.device)


@cache_outside_compile(maxsize=128)
def _filter_matrix(
    n: int, taps: tuple[float, ...], mode: str, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    # cached: building it is ~2 x len(taps) small ops, and a training step filters a dozen times (an 11-tap
    # SSIM window: uncached, these would be a sixth of the tiny model's torch calls per iteration)
    p = len(taps) // 2
    # a normal tensor even when first asked for under inference_mode, so that autograd may save it later
    with torch.inference_mode(False):
        padded = F.pad(torch.eye(n, dtype=dtype, device=device), (p, p), mode=mode)  # (n, n + 2p)
        return sum(w * padded[:, t : t + n] for t, w in enumerate(taps))


@torch.library.custom_op("unicorn::filter_matrix", mutates_args=())
def _cached_filter_matrix(
    n: int, taps: list[float], mode: str, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """A copy of the cached matrix (an operator's output may not alias memory that outlives it)."""
    if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
        # memory allocated while a CUDA graph is recorded belongs to its pool: not for the cache (graphs first run
        # eagerly, which fills the cache before they are recorded)
        return _filter_matrix.__wrapped__(n, tuple(taps), mode, dtype, device)
    return _filter_matrix(n, tuple(taps), mode, dtype, device).clone()


@_cached_filter_matrix.register_fake
def _(n: int, taps: list[float], mode: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.empty(n, n, dtype=dtype, device=device)


def separable_filter(x: torch.Tensor, taps_y: list[float], taps_x: list[float], mode: str) -> torch.Tensor:
    """Correlate (..., H, W) maps with ``taps_y`` along rows and ``taps_x`` along columns; the size is kept.

    Equal (to rounding) to padding by ``len(taps) // 2`` in ``mode`` and a 2-D correlation with the outer
    product ``taps_y x taps_x``.
    """
    rows = filter_matrix(x.shape[-2], taps_y, mode, x)
    cols = filter_matrix(x.shape[-1], taps_x, mode, x)
    return rows.transpose(0, 1) @ x @ cols
