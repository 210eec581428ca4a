"""Batch augmentation: the hue shift against a per-pixel HSV computation (colorsys)."""

from __future__ import annotations

import colorsys

import pytest
import torch

from unicorn.data.augment import random_hue_shift


def _shift_pixelwise(image: torch.Tensor, fraction: float) -> torch.Tensor:
    """(3, H, W) with every pixel's hue moved by ``fraction`` of the circle, one pixel at a time."""
    out = torch.empty_like(image)
    for i in range(image.shape[1]):
        for j in range(image.shape[2]):
            h, s, v = colorsys.rgb_to_hsv(*image[:, i, j].tolist())
            out[:, i, j] = torch.tensor(colorsys.hsv_to_rgb((h + fraction) % 1.0, s, v))
    return out


def test_each_image_gets_its_own_shift_within_range():
    images = torch.rand(6, 3, 5, 4, dtype=torch.float64)
    max_shift = 0.3
    shifted = random_hue_shift(images, max_shift, torch.Generator().manual_seed(7))
    # the draws: the same stream, as the function documents (uniform in [-max_shift, max_shift])
    fractions = (torch.rand(6, generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 2 - 1) * max_shift
    assert fractions.abs().max() <= max_shift and len(set(fractions.tolist())) == 6
    for b in range(6):
        torch.testing.assert_close(shifted[b], _shift_pixelwise(images[b], float(fractions[b])), atol=1e-6, rtol=0)
    assert shifted.min() >= 0 and shifted.max() <= 1


def test_greys_are_unchanged_and_zero_is_identity():
    grey = torch.rand(3, 1, 4, 4).expand(3, 3, 4, 4).contiguous()  # white, black and shades of grey
    torch.testing.assert_close(random_hue_shift(grey, 0.5, torch.Generator().manual_seed(0)), grey, atol=1e-6, rtol=0)
    images = torch.rand(2, 3, 4, 4)
    assert random_hue_shift(images, 0.0, torch.Generator().manual_seed(0)) is images


def test_same_generator_same_shifts():
    images = torch.rand(4, 3, 4, 4)
    a = random_hue_shift(images, 0.5, torch.Generator().manual_seed(3))
    b = random_hue_shift(images, 0.5, torch.Generator().manual_seed(3))
    c = random_hue_shift(images, 0.5, torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.allclose(a, c)


@pytest.mark.parametrize("max_shift", [-0.1, 0.6])
def test_shift_out_of_range_is_an_error(max_shift):
    with pytest.raises(ValueError, match="max_shift must be in"):
        random_hue_shift(torch.rand(1, 3, 2, 2), max_shift, torch.Generator())


def test_images_must_be_rgb_batches():
    with pytest.raises(ValueError, match="images"):
        random_hue_shift(torch.rand(3, 2, 2), 0.5, torch.Generator())
