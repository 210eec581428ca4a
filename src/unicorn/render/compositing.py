"""Shared plumbing of the aggregators: per-pixel slot layout and writing pixels back into images."""

from __future__ import annotations

import torch

from ..checks import check_shape
from .fragments import Fragments
from .raster import RenderError

__all__ = ["background_pixels", "gather_slots", "write_pixels"]


def gather_slots(fragments: Fragments, *values: torch.Tensor, fill: float = 0.0) -> tuple[torch.Tensor, ...]:
    """Lay packed per-pair values out as (R, K, ...) per covered pixel, slot order = depth order.

    Args:
        fragments: M packed pairs over R covered pixels with at most K slots each.
        values: tensors of shape (M, ...).
        fill: value of the empty slots.

    Returns:
        ``row_pix`` (R,) flat indices of the covered pixels, then one (R, K, ...) tensor per value.
    """
    row, row_pix = fragments.rows()
    R, K = row_pix.shape[0], fragments.slot_columns
    out = []
    for value in values:
        dense = value.new_full((R, K, *value.shape[1:]), fill)
        out.append(dense.index_put((row, fragments.slot), value))
    return (row_pix, *out)


def background_pixels(
    background: torch.Tensor | None,
    color: torch.Tensor,
    batch_size: int,
    image_size: tuple[int, int],
    num_channels: int,
    like: torch.Tensor,
) -> torch.Tensor:
    """Background as a flat (B * H * W, C) table, from an image (B, C, H, W) or the constant ``color`` (C,)."""
    H, W = image_size
    if background is None:
        if color.numel() != num_channels:
            raise RenderError(
                f"background_color has {color.numel()} channels, textures {num_channels}: give the renderer "
                f"{num_channels} background_color values, or a background image"
            )
        return color.to(like).expand(batch_size * H * W, num_channels)
    check_shape(background, "B, C, H, W", "background", {"B": batch_size, "C": num_channels, "H": H, "W": W})
    return background.to(like).permute(0, 2, 3, 1).reshape(-1, num_channels)


def write_pixels(
    bg_table: torch.Tensor,
    row_pix: torch.Tensor,
    rgb_rows: torch.Tensor,
    alpha_rows: torch.Tensor,
    batch_size: int,
    image_size: tuple[int, int],
) -> torch.Tensor:
    """Images (B, C + 1, H, W): the background everywhere, the composited rows at the covered pixels."""
    H, W = image_size
    C = bg_table.shape[1]
    rgb = bg_table.index_put((row_pix,), rgb_rows.to(bg_table.dtype))
    alpha = bg_table.new_zeros(bg_table.shape[0]).index_put((row_pix,), alpha_rows.to(bg_table.dtype))
    out = torch.cat([rgb, alpha.unsqueeze(1)], dim=1)
    return out.view(batch_size, H, W, C + 1).permute(0, 3, 1, 2)
