"""The loaders' decode, crop and resize steps give exactly what plain reference code gives, item for item.

The references below are the direct formulations: crops by clipped indices (clipping is numpy's ``edge`` padding)
times an in-image mask, one PIL resize per channel slice, ``convert("RGB")`` then a float division.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import unicorn.data.annotated as annotated
import unicorn.data.folder as folder
import unicorn.data.framing as framing
import unicorn.data.images as images
from tests.support.datasets import write_photo
from unicorn.data.cub import CUB200
from unicorn.data.folder import ImageFolder


def reference_crop(arr: np.ndarray, bbox: np.ndarray, edge: bool) -> np.ndarray:
    x1, y1, x2, y2 = (int(v) for v in bbox)
    H, W = arr.shape[:2]
    rows, cols = np.arange(y1, y2 + 1), np.arange(x1, x2 + 1)
    crop = arr[np.clip(rows, 0, H - 1)][:, np.clip(cols, 0, W - 1)]
    if not edge:
        inside = ((rows >= 0) & (rows < H))[:, None] & ((cols >= 0) & (cols < W))[None, :]
        crop = crop * inside.reshape(inside.shape + (1,) * (arr.ndim - 2))
    return crop


def reference_crop_box(image, bbox, mask=None):
    return reference_crop(image, bbox, True), None if mask is None else reference_crop(mask, bbox, False)


def reference_resize(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if arr.shape[:2] == tuple(size):
        return arr
    channels = [
        np.asarray(Image.fromarray(arr[..., c]).resize((size[1], size[0]), Image.Resampling.BILINEAR))
        for c in range(arr.shape[2])
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def reference_fit_and_pad(image: np.ndarray, size: int) -> np.ndarray:
    H, W = image.shape[:2]
    scale = size / max(H, W)
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    resized = reference_resize(image, (h, w))
    top, left = (size - h) // 2, (size - w) // 2
    return np.pad(resized, [(top, size - h - top), (left, size - w - left), (0, 0)], mode="edge")


def reference_rgb(img: Image.Image, name: str = "") -> np.ndarray:
    return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0


def test_crops_match_clipped_indexing() -> None:
    rng = np.random.default_rng(0)
    for trial in range(2000):
        H, W = (int(v) for v in rng.integers(1, 24, 2))
        shape = (H, W, 3) if trial % 2 else (H, W)
        arr = rng.random(shape).astype(np.float32) if trial % 3 else rng.integers(0, 256, shape, dtype=np.uint8)
        x1, y1 = (int(v) for v in rng.integers(-30, 30, 2))
        side = int(rng.integers(0, 40))
        bbox = np.array([x1, y1, x1 + side, y1 + side])  # inside, across the border, or off the array
        for edge in (True, False):
            got, expected = framing._crop_padded(arr, bbox, edge), reference_crop(arr, bbox, edge)
            assert got.dtype == expected.dtype and got.shape == expected.shape, (bbox, edge)
            assert np.array_equal(got, expected), (bbox, edge)
            assert not np.shares_memory(got, arr)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_resize_matches_per_channel_resizing(dtype) -> None:
    rng = np.random.default_rng(1)
    for H, W, size in [(37, 53, (16, 16)), (120, 90, (64, 64)), (8, 8, (32, 20)), (64, 64, (64, 64))]:
        arr = rng.random((H, W, 3)).astype(dtype)
        got, expected = framing.resize_image(arr, size), reference_resize(arr, size)
        assert got.dtype == expected.dtype and np.array_equal(got, expected)


@pytest.mark.parametrize("mode", ["RGB", "L", "P", "CMYK", "YCbCr", "1"])
def test_rgb_conversion_matches_convert_and_divide(mode: str) -> None:
    rgb = Image.fromarray(np.random.default_rng(2).integers(0, 256, (20, 30, 3), dtype=np.uint8))
    img = rgb.convert(mode)
    got = images._pil_to_rgb(img, "test.png")
    assert got.dtype == np.float32 and got.flags.writeable and np.array_equal(got, reference_rgb(img))


@pytest.fixture
def references(monkeypatch: pytest.MonkeyPatch):
    """Switch the loaders to the reference steps (inside the ``with``)."""

    class Switch:
        def __enter__(self) -> None:
            monkeypatch.setattr(annotated, "crop_box", reference_crop_box)
            monkeypatch.setattr(annotated, "resize_image", reference_resize)
            monkeypatch.setattr(folder, "fit_and_pad", reference_fit_and_pad)
            monkeypatch.setattr(images, "_pil_to_rgb", reference_rgb)

        def __exit__(self, *exc: object) -> None:
            monkeypatch.undo()

    return Switch()


def _items(dataset, n: int) -> list[dict]:
    torch.manual_seed(0)  # the same jitter and flips
    return [dataset[i % len(dataset)] for i in range(n)]


def _assert_same(got: list[dict], expected: list[dict]) -> None:
    for a, b in zip(got, expected, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key


def test_cub_items_are_the_reference_items(cub_root: Path, references) -> None:
    for split, eval_size in (("train", None), ("val", 256)):  # train: jittered, flipped crops
        dataset = CUB200(cub_root, split, img_size=64, eval_size=eval_size)
        with references:
            expected = _items(dataset, 12)
        _assert_same(_items(dataset, 12), expected)


def test_folder_items_are_the_reference_items(tmp_path: Path, references) -> None:
    for i, (w, h) in enumerate([(120, 80), (75, 140), (64, 64), (33, 97)]):
        write_photo(tmp_path / f"p{i}.jpg", w, h, seed=i)
        write_photo(tmp_path / f"q{i}.png", h, w, seed=10 + i)
    dataset = ImageFolder(tmp_path, img_size=64, augment=True)
    with references:
        expected = _items(dataset, 16)
    _assert_same(_items(dataset, 16), expected)
