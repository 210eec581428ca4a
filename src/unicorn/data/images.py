"""Image loading and the crop / pad / resize / flip steps shared by the loaders.

Arrays are numpy ``(H, W, 3)`` float32 in [0, 1] until :func:`to_chw_tensor` turns them into ``(C, H, W)``
tensors. Every decode goes through :func:`open_image`: any failure (truncated, not an image, an unknown
format, a decompression bomb) is an :class:`ImageLoadError`, and an image of more than :func:`max_image_pixels`
pixels is refused from its header before it is decoded (raise the limit with ``UNICORN_MAX_IMAGE_PIXELS``,
``dataset.max_image_pixels`` or the tools' ``--max-image-pixels``).

Bounding boxes are ``(x1, y1, x2, y2)`` in 0-based pixel indices, inclusive on both ends. Keypoints
are ``(K, 3)`` arrays of ``(column, row, visible)`` with pixel centres at integer coordinates.
"""

from __future__ import annotations

import contextlib
import io
import os
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np
import torch
from PIL import Image

from unicorn.errors import UserError

__all__ = [
    "DEFAULT_MAX_IMAGE_PIXELS",
    "MAX_IMAGE_PIXELS_ENV",
    "DatasetError",
    "DatasetNotFoundError",
    "ImageLoadError",
    "crop_box",
    "decode_image",
    "fit_and_pad",
    "hflip_keypoints",
    "jitter_bbox",
    "load_image",
    "load_mask",
    "max_image_pixels",
    "open_image",
    "pad_bbox",
    "resize_image",
    "resize_mask",
    "require",
    "set_max_image_pixels",
    "square_bbox",
    "to_chw_tensor",
]


class ImageLoadError(UserError, RuntimeError):
    """An image file (or LMDB record) could not be read or decoded; the message names it."""

    def __init__(self, path: str | os.PathLike, reason: str) -> None:
        self.path = str(path)
        super().__init__(f"cannot read image {self.path}: {reason}")


class DatasetError(UserError, ValueError):
    """A dataset that cannot be used as given: an unknown name, split or category, a malformed annotation file,
    no readable item (the message names it)."""


class DatasetNotFoundError(UserError, FileNotFoundError):
    """A dataset root or annotation file is missing; the message says where the data comes from."""

    def __init__(self, path: str | os.PathLike, what: str, hint: str) -> None:
        self.path = str(path)
        super().__init__(f"{what} not found at {self.path}. {hint}")


def require(path: str | os.PathLike, what: str, hint: str) -> Path:
    """Return ``path`` as a Path, or raise :class:`DatasetNotFoundError` if it does not exist."""
    path = Path(path).expanduser()
    if not path.exists():
        raise DatasetNotFoundError(path, what, hint)
    return path


#: pixels above which an image is refused: where PIL itself refuses (2 x its warning threshold), about 13400^2
DEFAULT_MAX_IMAGE_PIXELS = 178_956_970
#: environment variable holding the limit (inherited by DataLoader workers); 0 means no limit
MAX_IMAGE_PIXELS_ENV = "UNICORN_MAX_IMAGE_PIXELS"
_PIL_LOCK = threading.Lock()


def max_image_pixels() -> int | None:
    """The current limit on pixels per image (None: no limit); see :func:`set_max_image_pixels`."""
    text = os.environ.get(MAX_IMAGE_PIXELS_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_IMAGE_PIXELS
    try:
        value = int(float(text))
    except ValueError:
        raise ImageLimitError(f"{MAX_IMAGE_PIXELS_ENV}={text!r} is not a number of pixels") from None
    return value if value > 0 else None


def set_max_image_pixels(limit: int | None) -> None:
    """Set the limit on pixels per image for this process and its children (None or 0: no limit).

    Raises:
        ImageLimitError: a negative limit.
    """
    if limit is not None and limit < 0:
        raise ImageLimitError(f"the image pixel limit must be >= 0 (0: none), got {limit}")
    os.environ[MAX_IMAGE_PIXELS_ENV] = str(int(limit or 0))


class ImageLimitError(UserError, ValueError):
    """An invalid image pixel limit."""


@contextlib.contextmanager
def open_image(source: str | os.PathLike | IO[bytes], name: str | os.PathLike) -> Iterator[Image.Image]:
    """``PIL.Image.open`` with the pixel limit and one error type; ``name`` is used in errors.

    Yields the opened (not yet loaded) image. Any exception while opening or inside the block becomes an
    :class:`ImageLoadError` naming ``name``.
    """
    limit = max_image_pixels()
    try:
        with _PIL_LOCK, warnings.catch_warnings():
            # PIL's global bomb check is replaced by the header check below (its limit is not ours)
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                img = Image.open(source)  # reads the header only
            finally:
                Image.MAX_IMAGE_PIXELS = saved
        with img:
            pixels = img.width * img.height
            if limit is not None and pixels > limit:
                raise ImageLoadError(
                    name,
                    f"{img.width}x{img.height} = {pixels} pixels exceeds the limit of {limit} (a decompression "
                    f"bomb?); if the image is genuine raise the limit with --max-image-pixels, "
                    f"dataset.max_image_pixels or {MAX_IMAGE_PIXELS_ENV}",
                )
            yield img
    except ImageLoadError:
        raise
    except Exception as err:  # PIL raises many kinds on bad files (OSError, SyntaxError, struct.error, ...)
        raise ImageLoadError(name, f"{type(err).__name__}: {' '.join(str(err).split())}") from err


def _pil_to_rgb(img: Image.Image) -> np.ndarray:
    """Any PIL mode to an (H, W, 3) float32 RGB array in [0, 1]."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        # 16-bit (or 32-bit int) grayscale: PIL's convert('L') clips instead of rescaling
        arr = np.asarray(img, dtype=np.float64)
        peak = 65535.0 if img.mode.startswith("I;16") or arr.max() > 255 else 255.0
        gray = np.clip(arr / peak, 0.0, 1.0).astype(np.float32)
        return np.repeat(gray[..., None], 3, axis=-1)
    if img.mode == "F":
        gray = np.clip(np.asarray(img, dtype=np.float32), 0.0, 1.0)
        return np.repeat(gray[..., None], 3, axis=-1)
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        # composite transparent pixels on white, the NMR / ShapeNet background
        rgba = np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0
        alpha = rgba[..., 3:]
        return rgba[..., :3] * alpha + (1.0 - alpha)
    return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as RGB.

    Grayscale, palette, RGBA (composited on white), CMYK and 16-bit images are converted.

    Args:
        path: image file.

    Returns:
        (H, W, 3) float32 array in [0, 1].

    Raises:
        ImageLoadError: if the file is missing, truncated or not an image.
    """
    with open_image(path, path) as img:
        img.load()
        return _pil_to_rgb(img)


def decode_image(data: bytes, name: str) -> np.ndarray:
    """Decode encoded image bytes (e.g. an LMDB value) like :func:`load_image`; ``name`` is used in errors."""
    with open_image(io.BytesIO(data), name) as img:
        img.load()
        return _pil_to_rgb(img)


def load_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a mask image (any mode, first channel) as an (H, W) float32 array in {0, 1}."""
    with open_image(path, path) as img:
        img.load()
        arr = np.asarray(img)
    if arr.ndim == 3:
        arr = arr[..., 0]
    return (arr > arr.max() / 2 if arr.max() > 0 else arr > 0).astype(np.float32)


def to_chw_tensor(arr: np.ndarray) -> torch.Tensor:
    """(H, W, C) or (H, W) array to a contiguous float32 tensor (C, H, W) / (1, H, W)."""
    if arr.ndim == 2:
        arr = arr[..., None]
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1), dtype=np.float32))


def resize_image(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W, 3) [0, 1] image to ``size = (H', W')`` with antialiased bilinear filtering."""
    if arr.shape[:2] == tuple(size):
        return arr
    channels = [
        np.asarray(Image.fromarray(arr[..., c]).resize((size[1], size[0]), Image.Resampling.BILINEAR))
        for c in range(arr.shape[2])
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W) {0, 1} mask to ``size = (H', W')`` with nearest-neighbour sampling."""
    if mask.shape[:2] == tuple(size):
        return mask.astype(np.float32)
    img = Image.fromarray((mask > 0.5).astype(np.uint8) * 255)
    return (np.asarray(img.resize((size[1], size[0]), Image.Resampling.NEAREST)) > 127).astype(np.float32)


def pad_bbox(bbox: np.ndarray, frac: float) -> np.ndarray:
    """Grow an (x1, y1, x2, y2) box by ``frac`` of its width / height on every side."""
    x1, y1, x2, y2 = np.asarray(bbox, dtype=np.float64)
    bw, bh = x2 - x1 + 1, y2 - y1 + 1
    return np.array([x1 - frac * bw, y1 - frac * bh, x2 + frac * bw, y2 + frac * bh])


def jitter_bbox(bbox: np.ndarray, frac: float, rng: np.random.Generator) -> np.ndarray:
    """Move every coordinate of a box by ``U(-1, 1) * frac`` times the box width (x) or height (y)."""
    x1, y1, x2, y2 = np.asarray(bbox, dtype=np.float64)
    bw, bh = x2 - x1 + 1, y2 - y1 + 1
    u = rng.uniform(-1.0, 1.0, size=4)
    return np.array([x1 + u[0] * frac * bw, y1 + u[1] * frac * bh, x2 + u[2] * frac * bw, y2 + u[3] * frac * bh])


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


def _crop_padded(arr: np.ndarray, bbox: np.ndarray, edge: bool) -> np.ndarray:
    """Crop ``arr[y1:y2+1, x1:x2+1]`` where the box may leave the array.

    Outside pixels replicate the nearest border pixel (``edge=True``) or are zero.
    """
    x1, y1, x2, y2 = (int(v) for v in bbox)
    H, W = arr.shape[:2]
    rows, cols = np.arange(y1, y2 + 1), np.arange(x1, x2 + 1)
    # clipped indices are exactly numpy's 'edge' padding, for any box, even one entirely outside
    crop = arr[np.clip(rows, 0, H - 1)][:, np.clip(cols, 0, W - 1)]
    if not edge:
        inside = ((rows >= 0) & (rows < H))[:, None] & ((cols >= 0) & (cols < W))[None, :]
        crop = crop * inside.reshape(inside.shape + (1,) * (arr.ndim - 2))
    return crop


def crop_box(
    image: np.ndarray, bbox: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Crop an integer box, replicating the image's border pixels and zero-padding the mask outside it.

    Args:
        image: (H, W, 3) array.
        bbox: int ``(x1, y1, x2, y2)``, e.g. from :func:`square_bbox`; it may leave the image.
        mask: optional (H, W) array.

    Returns:
        (h, w, 3) crop and the (h, w) mask crop (or None), with h = y2 - y1 + 1 and w = x2 - x1 + 1.
    """
    crop = _crop_padded(image, bbox, edge=True)
    mask_crop = None if mask is None else _crop_padded(mask, bbox, edge=False)
    return crop, mask_crop


def fit_and_pad(image: np.ndarray, size: int) -> np.ndarray:
    """Resize so the longer side is ``size`` (aspect kept), then pad the shorter side to a square.

    The padding replicates the border pixels and centres the image, as the reference's ``SquarePad``.

    Returns:
        (size, size, 3) array.
    """
    H, W = image.shape[:2]
    scale = size / max(H, W)
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    resized = resize_image(image, (h, w))
    top, left = (size - h) // 2, (size - w) // 2
    return np.pad(resized, [(top, size - h - top), (left, size - w - left), (0, 0)], mode="edge")


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
