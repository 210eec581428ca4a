"""Hard aggregation: the colour of the nearest face containing the pixel, optionally averaged over supersamples.

With fragments at ``s`` times the output resolution (a supersampling rasterizer), every output pixel is
the mean of its ``s x s`` subpixels composited over black, plus the background where that mean's alpha is
below 1; this anti-aliases edges. Gradients reach colours and the background, not vertex positions.
"""

from __future__ import annotations

import torch
import torch.nn.functional as nnf
from torch import nn

from .fragments import Fragments, check_blend_inputs
from .layered import layered_blend
from .raster import check_whole_number

__all__ = ["HardBlend", "hard_blend"]


def hard_blend(
    colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor, supersample: int = 1
) -> torch.Tensor:
    """Composite the nearest face containing each (sub)pixel over a background.

    Args:
        colors: (M, C) colour of every pair.
        fragments: the packed fragments at (s * H, s * W) (near-miss pairs are ignored).
        bg_table: (B * H * W, C) background colour of every output pixel.
        supersample: s >= 1, the rasterizer's supersampling factor.

    Returns:
        (B, C + 1, H, W) images, the last channel the covered fraction of each pixel's subpixels.
    """
    check_whole_number("supersample", supersample, 1)
    s = int(supersample)
    B = fragments.batch_size
    h, w = fragments.image_size
    H, W = h // s, w // s
    if s != supersample or h % s or w % s:
        raise ValueError(f"fragments at {h}x{w} are not a supersampling by {supersample} of {B} images")
    check_blend_inputs(colors, fragments, bg_table, pixels=B * H * W)
    C = colors.shape[1]
    # composite premultiplied colour over black at full resolution, average, then add the background
    fine = layered_blend(colors, fragments, colors.new_zeros(C).expand(B * h * w, C), sigma=0.0)
    coarse = nnf.avg_pool2d(fine, s) if s > 1 else fine
    bg = bg_table.reshape(B, H, W, C).permute(0, 3, 1, 2)
    alpha = coarse[:, -1:]
    return torch.cat([coarse[:, :-1] + (1 - alpha) * bg, alpha], dim=1)


class HardBlend(nn.Module):
    """Module form of :func:`hard_blend` holding the supersampling factor (the rasterizer's)."""

    def __init__(self, supersample: int = 1) -> None:
        super().__init__()
        check_whole_number("supersample", supersample, 1)
        self.supersample = int(supersample)

    def extra_repr(self) -> str:
        return f"supersample={self.supersample}"

    def forward(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return hard_blend(colors, fragments, bg_table, self.supersample)
