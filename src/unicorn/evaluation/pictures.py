"""Picture helpers of the reports: uint8 conversion, mask overlays, labelled image grids, GIF animations."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

__all__ = ["image_grid", "mask_overlay", "save_gif", "to_uint8"]


# ---------------------------------------------------------------------------------------------- pictures
def to_uint8(image: torch.Tensor | np.ndarray, size: int | None = None) -> np.ndarray:
    """(C, H, W) tensor or (H, W, C) / (H, W) array in [0, 1] to an (H', W', 3) uint8 array (resized bicubically)."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().float()
        image = image.permute(1, 2, 0).numpy() if image.dim() == 3 else image.numpy()
    arr = np.asarray(image, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.shape[-1] == 1:
        arr = np.repeat(arr, 3, axis=-1)
    arr = (np.clip(arr[..., :3], 0, 1) * 255).round().astype(np.uint8)
    if size is not None and arr.shape[:2] != (size, size):
        arr = np.asarray(Image.fromarray(arr).resize((size, size), Image.Resampling.BICUBIC))
    return arr


def mask_overlay(alpha: torch.Tensor, mask: torch.Tensor | None) -> np.ndarray:
    """Predicted silhouette against the ground truth: both dark grey, prediction only red, ground truth only blue.

    Args:
        alpha: (1, H, W) predicted alpha; mask: (1, H, W) ground-truth mask, or None (prediction in grey).

    Returns:
        (H, W, 3) float array in [0, 1].
    """
    pred = alpha[0].detach().cpu().numpy() > 0.5
    out = np.ones((*pred.shape, 3), dtype=np.float32)
    if mask is None:
        out[pred] = (0.3, 0.3, 0.3)
        return out
    gt = mask[0].detach().cpu().numpy() > 0.5
    out[pred & gt] = (0.3, 0.3, 0.3)
    out[pred & ~gt] = (0.9, 0.25, 0.2)
    out[~pred & gt] = (0.2, 0.45, 0.9)
    return out


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    # Pillow's scalable default font; the bitmap one it falls back to without FreeType draws Latin-1 only
    return ImageFont.load_default(size=size)


def image_grid(
    rows: Sequence[Sequence[np.ndarray]],
    column_labels: Sequence[str],
    row_labels: Sequence[str] | None = None,
    pad: int = 4,
    label_width: int = 150,
) -> Image.Image:
    """A labelled grid of equally sized uint8 images.

    Args:
        rows: rows of (H, W, 3) uint8 images, all of one size.
        column_labels: one header per column.
        row_labels: text (lines separated by newlines) left of each row, or None.
        pad: pixels between cells.
        label_width: width of the row-label column.

    Returns:
        the grid as a PIL image.
    """
    H, W = rows[0][0].shape[:2]
    n_cols = max(len(r) for r in rows)
    font = _font(max(11, min(16, W // 9)))
    head = 24
    left = label_width if row_labels else 0
    grid = Image.new("RGB", (left + n_cols * (W + pad) + pad, head + len(rows) * (H + pad) + pad), "white")
    draw = ImageDraw.Draw(grid)
    for c, label in enumerate(column_labels[:n_cols]):
        draw.text((left + pad + c * (W + pad) + W // 2, head // 2), label, fill=(40, 40, 40), font=font, anchor="mm")
    for r, row in enumerate(rows):
        y = head + pad + r * (H + pad)
        for c, cell in enumerate(row):
            grid.paste(Image.fromarray(cell), (left + pad + c * (W + pad), y))
        if row_labels:
            draw.multiline_text((pad + 2, y + 4), row_labels[r], fill=(40, 40, 40), font=font, spacing=3)
    return grid


def save_gif(frames: torch.Tensor, path: str | os.PathLike, duration_ms: int = 80) -> Path:
    """Write (N, 3 or 4, H, W) frames in [0, 1] as a looping GIF (on white)."""
    path = Path(path)
    images = [Image.fromarray(to_uint8(f[:3])) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=duration_ms, loop=0, optimize=False)
    return path
