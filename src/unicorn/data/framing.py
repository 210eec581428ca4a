"""Framing an object in an image: boxes, crops, square padding, resizing and mirrored keypoints.

Images are numpy ``(H, W, 3)`` float32 arrays in [0, 1] and masks ``(H, W)`` (as :mod:`unicorn.data.images` loads
them). Bounding boxes are ``(x1, y1, x2, y2)`` in 0-based pixel indices, inclusive on both ends. Keypoints are
``(K, 3)`` arrays of ``(column, row, visible)`` with pixel centres at integer coordinates.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

__all__ = [
    "crop_box",
    "fit_and_pad",
    "fit_layout",
    "hflip_keypoints",
    "jitter_bbox",
    "pad_bbox",
    "resize_image",
    "resize_mask",
    "square_bbox",
]


def resize_image(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W, 3) [0, 1] image to ``size = (H', W')`` with antialiased bilinear filtering.

    Each channel is resized as a float32 PIL image; the channels are made contiguous planes once, so that PIL reads
    each without another copy.
    """
    if arr.shape[:2] == tuple(size):
        return arr
    planes = np.ascontiguousarray(np.moveaxis(arr, -1, 0))  # (3, H, W)
    channels = [
        np.asarray(Image.fromarray(plane).resize((size[1], size[0]), Image.Resampling.BILINEAR)) for plane in planes
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W) {0, 1} mask to ``size = (H', W')`` with nearest-neighbour sampling."""
    if mask.shape[:2] == tuple(size):
        return mask.astype(np.float32)
    img = Image.fromarray((mask > 0.5).astype(np.uint8) * 255)
    return (np.asarray(img.resize((size[1], size[0]), Image.Resampling.NEAREST)) > 127).astype(np.float32)


def _ordered(x1: float, y1: float, x2: float, y2: float) -> np.ndarray:
    """``(x1, y1, x2, y2)`` with ``x2 >= x1`` and ``y2 >= y1``: a far corner that crossed the near one is put on it,
    so that the box, rounded, still frames at least one pixel."""
    return np.array([x1, y1, max(x2, x1), max(y2, y1)])


def pad_bbox(bbox: np.ndarray, frac: float) -> np.ndarray:
    """Grow an (x1, y1, x2, y2) box by ``frac`` of its width / height on every side (shrink it when negative; a box
    shrunk past its centre keeps one pixel)."""
    x1, y1, x2, y2 = np.asarray(bbox, dtype=np.float64)
    bw, bh = x2 - x1 + 1, y2 - y1 + 1
    return _ordered(x1 - frac * bw, y1 - frac * bh, x2 + frac * bw, y2 + frac * bh)


def jitter_bbox(bbox: np.ndarray, frac: float, rng: np.random.Generator) -> np.ndarray:
    """Move every coordinate of a box by ``U(-1, 1) * frac`` times the box width (x) or height (y).

    Below 0.5 opposite corners cannot cross on a box of a few pixels or more; whatever ``frac``, a far corner moved
    past the near one is put on it (the box keeps one pixel).
    """
    x1, y1, x2, y2 = np.asarray(bbox, dtype=np.float64)
    bw, bh = x2 - x1 + 1, y2 - y1 + 1
    u = rng.uniform(-1.0, 1.0, size=4)
    return _ordered(x1 + u[0] * frac * bw, y1 + u[1] * frac * bh, x2 + u[2] * frac * bw, y2 + u[3] * frac * bh)


def square_bbox(bbox: np.ndarray) -> np.ndarray:
    """Round a box to integers and grow its shorter side symmetrically to the longer one.

    Returns:
        (4,) int64 ``(x1, y1, x2, y2)`` with ``x2 - x1 == y2 - y1``.
    """
    x1, y1, x2, y2 = np.round(np.asarray(bbox, dtype=np.float64)).astype(np.int64)
    w, h = x2 - x1 + 1, y2 - y1 + 1
    side = max(w, h)
    x1 -= (side - w) // 2
    y1 -= (side - h) // 2
    return np.array([x1, y1, x1 + side - 1, y1 + side - 1], dtype=np.int64)


def _crop_padded(arr: np.ndarray, bbox: np.ndarray, edge: bool, fill: float = 0.0) -> np.ndarray:
    """Crop ``arr[y1:y2+1, x1:x2+1]`` where the box may leave the array; always a new array.

    Outside pixels replicate the nearest border pixel (``edge=True``) or are ``fill``.
    """
    x1, y1, x2, y2 = (int(v) for v in bbox)
    H, W = arr.shape[:2]
    top, bottom, left, right = max(y1, 0), min(y2 + 1, H), max(x1, 0), min(x2 + 1, W)
    if top < bottom and left < right:
        # the part inside the array, padded: one slice and one copy
        widths = [(top - y1, y2 + 1 - bottom), (left - x1, x2 + 1 - right)] + [(0, 0)] * (arr.ndim - 2)
        if edge:
            return np.pad(arr[top:bottom, left:right], widths, mode="edge")
        return np.pad(arr[top:bottom, left:right], widths, mode="constant", constant_values=fill)
    # a box that misses the array entirely
    rows, cols = np.arange(y1, y2 + 1), np.arange(x1, x2 + 1)
    # clipped indices are exactly numpy's 'edge' padding, for any box, even one entirely outside
    crop = arr[np.clip(rows, 0, H - 1)][:, np.clip(cols, 0, W - 1)]
    if not edge:
        inside = ((rows >= 0) & (rows < H))[:, None] & ((cols >= 0) & (cols < W))[None, :]
        crop = np.where(inside.reshape(inside.shape + (1,) * (arr.ndim - 2)), crop, np.asarray(fill, crop.dtype))
    return crop


def crop_box(
    image: np.ndarray, bbox: np.ndarray, mask: np.ndarray | None = None, fill: float | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Crop an integer box, replicating the image's border pixels (or setting them to ``fill``) and zero-padding
    the mask outside it.

    Args:
        image: (H, W, 3) array.
        bbox: int ``(x1, y1, x2, y2)``, e.g. from :func:`square_bbox`; it may leave the image.
        mask: optional (H, W) array.
        fill: the image crop's value beyond the image's edges (a cut-out's white background); None: the border
            pixels repeated (a photo's).

    Returns:
        (h, w, 3) crop and the (h, w) mask crop (or None), with h = y2 - y1 + 1 and w = x2 - x1 + 1.
    """
    crop = _crop_padded(image, bbox, edge=fill is None, fill=fill or 0.0)
    mask_crop = None if mask is None else _crop_padded(mask, bbox, edge=False)
    return crop, mask_crop


def fit_and_pad(image: np.ndarray, size: int, fill: float | None = None) -> np.ndarray:
    """Resize so the longer side is ``size`` (aspect kept), then pad the shorter side to a square.

    The padding centres the image and replicates its border pixels, as the reference's ``SquarePad`` (or, given
    ``fill``, sets them to it: a cut-out's white background).

    Returns:
        (size, size, 3) array.
    """
    h, w, top, left = fit_layout(image.shape[0], image.shape[1], size)
    resized = resize_image(image, (h, w))
    widths = [(top, size - h - top), (left, size - w - left), (0, 0)]
    if fill is None:
        return np.pad(resized, widths, mode="edge")
    return np.pad(resized, widths, mode="constant", constant_values=fill)


def fit_layout(H: int, W: int, size: int) -> tuple[int, int, int, int]:
    """Where :func:`fit_and_pad` puts an (H, W) image in its (size, size) square: ``(h, w, top, left)``, the resized
    image's side lengths and its offset."""
    scale = size / max(H, W)
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    return h, w, (size - h) // 2, (size - w) // 2


def hflip_keypoints(keypoints: np.ndarray, width: int, perm: np.ndarray | None = None) -> np.ndarray:
    """Mirror (K, 3) ``(column, row, visible)`` keypoints for a horizontally flipped image of ``width``.

    Args:
        keypoints: (K, 3) array.
        width: image width in pixels.
        perm: (K,) 0-based permutation swapping left and right keypoints (e.g. CUB's LEye <-> REye).

    Returns:
        (K, 3) keypoints of the flipped image.
    """
    out = keypoints.copy()
    out[:, 0] = width - 1 - keypoints[:, 0]
    if perm is not None:
        out = out[np.asarray(perm)]
    return out
