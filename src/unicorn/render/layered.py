"""UNICORN's layered aggregation: front-to-back alpha compositing of face occupancies.

``O(p, f) = exp(min(0, -d(p, f)) / sigma)`` with ``d`` the signed squared NDC distance (negative inside), so
the occupancy is 1 inside a face and decays over about one pixel outside. Colours are composited as
``sum_l [prod_{k<l} (1 - O_k)] O_l c_l`` over the background (paper, supplementary "Custom differentiable
rendering").
"""

from __future__ import annotations

import torch
from torch import nn

from .compositing import gather_slots, write_pixels
from .fragments import Fragments

__all__ = ["LayeredBlend", "layered_blend", "layered_occupancy"]


def layered_occupancy(fragments: Fragments, sigma: float) -> torch.Tensor:
    """Occupancy (M,) of every pair: 1 inside the face, ``exp(-d / sigma)`` outside; a hard 0/1 if sigma = 0."""
    if sigma == 0:
        return fragments.inside.to(fragments.dists.dtype)
    outside = torch.exp(-fragments.dists.clamp_min(0.0) / sigma)
    return torch.where(fragments.inside, torch.ones_like(outside), outside)


def layered_blend(colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor, sigma: float) -> torch.Tensor:
    """Composite fragment colours front to back over a background.

    Args:
        colors: (M, C) colour of every pair.
        fragments: the packed fragments.
        bg_table: (B * H * W, C) background colour of every pixel.
        sigma: occupancy temperature on squared NDC distances (1e-4 in the reference); 0 gives hard edges.

    Returns:
        (B, C + 1, H, W) images, the last channel the alpha ``1 - prod_l (1 - O_l)``.
    """
    occupancy = layered_occupancy(fragments, sigma)
    row_pix, occ, col = gather_slots(fragments, occupancy, colors)
    transmit = torch.cumprod(1.0 - occ, dim=1)  # (R, K): light passing through slots 0..k
    before = torch.cat([torch.ones_like(transmit[:, :1]), transmit[:, :-1]], dim=1)
    rgb = ((before * occ).unsqueeze(-1) * col).sum(1) + transmit[:, -1:] * bg_table.index_select(0, row_pix)
    alpha = 1.0 - transmit[:, -1]
    return write_pixels(bg_table, row_pix, rgb, alpha, fragments.batch_size, fragments.image_size)


class LayeredBlend(nn.Module):
    """Module form of :func:`layered_blend` holding ``sigma``."""

    def __init__(self, sigma: float = 1e-4) -> None:
        super().__init__()
        if sigma < 0:
            raise ValueError(f"sigma must be >= 0, got {sigma}")
        self.sigma = float(sigma)

    def extra_repr(self) -> str:
        return f"sigma={self.sigma}"

    def forward(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return layered_blend(colors, fragments, bg_table, self.sigma)
