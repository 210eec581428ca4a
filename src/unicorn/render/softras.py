"""SoftRasterizer's aggregation (Liu et al. 2019), as the UNICORN paper's supplementary writes it.

Occupancy ``D = sigmoid(-d / sigma)`` (d signed squared NDC distance, negative inside), colour = softmax over
faces and background weighted by ``D * exp(z_inv / gamma)`` with ``z_inv = (zfar - z) / (zfar - znear)``, the
background a last layer with ``D = 1`` and ``z_inv = eps``; alpha ``1 - prod (1 - D)``.
Defaults: sigma = gamma = 1e-4, znear = 1, zfar = 100, eps = 1e-3.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .compositing import gather_slots, write_pixels
from .fragments import Fragments, check_blend_inputs
from .raster import RenderError, is_real

__all__ = ["SoftRasBlend", "check_depth_range", "check_temperatures", "softras_blend"]


#: the largest number that is 0 in float32 (half the smallest subnormal, which rounds to even: 0)
_FLOAT32_ZERO = 2.0**-150


def check_temperatures(sigma: float, gamma: float) -> None:
    """Raise RenderError unless the occupancy and depth temperatures are finite numbers (NumPy scalars included, bools
    not) > 0 in float32, where the renders divide by them."""
    if not all(is_real(t) and _FLOAT32_ZERO < t < math.inf for t in (sigma, gamma)):
        raise RenderError(f"sigma and gamma must be finite and > 0 in float32, got sigma={sigma}, gamma={gamma}")


def check_depth_range(znear: float, zfar: float, eps: float = 0.0) -> None:
    """Raise RenderError unless ``0 <= znear < zfar`` are finite and the background's ``eps`` is a finite number
    (NumPy scalars included, bools not)."""
    if not (all(is_real(v) and math.isfinite(v) for v in (znear, zfar, eps)) and 0 <= znear < zfar):
        raise RenderError(f"need finite 0 <= znear < zfar and a finite eps, got znear={znear}, zfar={zfar}, eps={eps}")


def softras_blend(
    colors: torch.Tensor,
    fragments: Fragments,
    bg_table: torch.Tensor,
    sigma: float = 1e-4,
    gamma: float = 1e-4,
    znear: float = 1.0,
    zfar: float = 100.0,
    eps: float = 1e-3,
) -> torch.Tensor:
    """Soft aggregation of fragment colours over a background.

    Args:
        colors: (M, C) colour of every pair.
        fragments: the packed fragments (not truncated: every face within the blur radius counts).
        bg_table: (B * H * W, C) background colour of every pixel.
        sigma: occupancy temperature on squared NDC distances.
        gamma: depth softmax temperature.
        znear, zfar: depth normalisation range.
        eps: normalised inverse depth of the background layer.

    Returns:
        (B, C + 1, H, W) images, the last channel the alpha.
    """
    check_blend_inputs(colors, fragments, bg_table)
    check_temperatures(sigma, gamma)
    check_depth_range(znear, zfar, eps)
    prob = torch.sigmoid(-fragments.dists / sigma)
    z_inv = (zfar - fragments.zbuf) / (zfar - znear)
    row_pix, prob_k, z_inv_k, col = gather_slots(fragments, prob, z_inv, colors)
    valid = gather_slots(fragments, torch.ones_like(prob))[1]
    # the softmax is shift-invariant: subtract the per-pixel max for stability
    z_max = torch.where(valid > 0, z_inv_k, torch.full_like(z_inv_k, -torch.inf)).amax(1, keepdim=True)
    z_max = z_max.clamp_min(eps).detach()
    w_faces = prob_k * torch.exp((z_inv_k - z_max) / gamma) * valid
    w_bg = torch.exp((eps - z_max) / gamma)
    norm = w_faces.sum(1, keepdim=True) + w_bg
    rgb = ((w_faces.unsqueeze(-1) * col).sum(1) + w_bg * bg_table.index_select(0, row_pix)) / norm
    alpha = 1.0 - torch.prod(1.0 - prob_k, dim=1)
    return write_pixels(bg_table, row_pix, rgb, alpha, fragments.batch_size, fragments.image_size)


class SoftRasBlend(nn.Module):
    """Module form of :func:`softras_blend` holding its hyperparameters (see there)."""

    #: the rasterizer's supersampling it takes: fragments at the image size (:class:`~unicorn.render.MeshRenderer`)
    supersample = 1

    def __init__(
        self,
        sigma: float = 1e-4,
        gamma: float = 1e-4,
        znear: float = 1.0,
        zfar: float = 100.0,
        eps: float = 1e-3,
    ) -> None:
        super().__init__()
        check_temperatures(sigma, gamma)
        check_depth_range(znear, zfar, eps)
        self.sigma, self.gamma, self.eps = float(sigma), float(gamma), float(eps)
        self.znear, self.zfar = float(znear), float(zfar)

    def extra_repr(self) -> str:
        return f"sigma={self.sigma}, gamma={self.gamma}, znear={self.znear}, zfar={self.zfar}, eps={self.eps}"

    def forward(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return softras_blend(colors, fragments, bg_table, self.sigma, self.gamma, self.znear, self.zfar, self.eps)
