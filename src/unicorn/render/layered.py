"""UNICORN's layered aggregation: front-to-back alpha compositing of face occupancies.

``O(p, f) = exp(min(0, -d(p, f)) / sigma)`` with ``d`` the signed squared NDC distance (negative inside), so
the occupancy is 1 inside a face and decays over about one pixel outside. Colours are composited as
``sum_l [prod_{k<l} (1 - O_k)] O_l c_l`` over the background (paper, supplementary "Custom differentiable
rendering").
"""

from __future__ import annotations

import torch
from torch import nn

from .compositing import write_pixels
from .fragments import Fragments, check_blend_inputs
from .raster import check_sigma

__all__ = ["LayeredBlend", "layered_blend", "layered_occupancy"]


def layered_occupancy(fragments: Fragments, sigma: float) -> torch.Tensor:
    """Occupancy (M,) of every pair: 1 inside the face, ``exp(-d / sigma)`` outside; a hard 0/1 if sigma = 0.

    Raises:
        RenderError: ``sigma`` is not a finite number >= 0.
    """
    check_sigma(sigma)
    if sigma == 0:
        return fragments.inside.to(fragments.dists.dtype)
    outside = torch.exp(-fragments.dists.clamp_min(0.0) / sigma)
    return torch.where(fragments.inside, torch.ones_like(outside), outside)


def layered_blend(colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor, sigma: float) -> torch.Tensor:
    """Composite fragment colours front to back over a background.

    Works on the packed pairs directly (no padded per-pixel layout): the transmittance in front of every pair is
    an exclusive running product within its pixel, computed as a running sum of ``log(1 - O)`` in float64. A
    face containing the pixel (O = 1) hides everything behind it exactly.

    Args:
        colors: (M, C) colour of every pair.
        fragments: the packed fragments.
        bg_table: (B * H * W, C) background colour of every pixel.
        sigma: occupancy temperature on squared NDC distances (1e-4 in the reference); 0 gives hard edges.

    Returns:
        (B, C + 1, H, W) images, the last channel the alpha ``1 - prod_l (1 - O_l)``.
    """
    check_blend_inputs(colors, fragments, bg_table)
    occupancy = layered_occupancy(fragments, sigma)
    row, row_pix = fragments.rows()
    R = row_pix.shape[0]
    # counted by index_add, not bincount, which reads its size back on CUDA; rows without pairs (fixed buffers)
    # read pair 0 below, and their sums are zeroed
    counts = torch.zeros(R, dtype=torch.long, device=row.device).index_add_(0, row, torch.ones_like(row))
    first = torch.cumsum(counts, 0) - counts  # index of each pixel's nearest pair
    last = first + counts - 1
    if fragments.valid is not None:
        first, last = first.clamp(max=max(row.numel() - 1, 0)), last.clamp(min=0)

    def exclusive_in_pixel(values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per pair: the sum over the pairs in front of it in its pixel; per pixel: the sum over all its pairs."""
        running = torch.cumsum(values, 0)
        before_pixel = (running - values).index_select(0, first)
        total = running.index_select(0, last) - before_pixel
        if fragments.valid is not None:
            total = torch.where(counts > 0, total, 0)
        return running - values - before_pixel.index_select(0, row), total

    # an opaque pair (inside its face) contributes through the mask below, not through log(0)
    log_clear = torch.where(
        fragments.inside, torch.zeros_like(occupancy), torch.log1p(-occupancy.clamp(max=1.0 - 1e-6))
    ).double()
    log_front, log_all = exclusive_in_pixel(log_clear)
    opaque_front, opaque_all = exclusive_in_pixel(fragments.inside.long())
    front = torch.exp(log_front).to(occupancy.dtype) * (opaque_front == 0)
    through = torch.exp(log_all).to(occupancy.dtype) * (opaque_all == 0)  # (R,) light reaching the background

    weighted = (front * occupancy).unsqueeze(1) * colors
    rgb = colors.new_zeros(R, colors.shape[1]).index_add(0, row, weighted)
    rgb = rgb + through.unsqueeze(1) * bg_table.index_select(0, row_pix)
    return write_pixels(bg_table, row_pix, rgb, 1.0 - through, fragments.batch_size, fragments.image_size)


class LayeredBlend(nn.Module):
    """Module form of :func:`layered_blend` holding ``sigma``."""

    #: the rasterizer's supersampling it takes: fragments at the image size (:class:`~unicorn.render.MeshRenderer`)
    supersample = 1

    def __init__(self, sigma: float = 1e-4) -> None:
        super().__init__()
        check_sigma(sigma)
        self.sigma = float(sigma)

    def extra_repr(self) -> str:
        return f"sigma={self.sigma}"

    def forward(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return layered_blend(colors, fragments, bg_table, self.sigma)
