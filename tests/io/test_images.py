"""User images for unicorn-reconstruct: orientation, and the checks every loader shares."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.support.datasets import save_with_orientation
from unicorn.data.framing import fit_and_pad
from unicorn.data.images import ImageLoadError
from unicorn.io import alpha_bbox, load_input, read_input


def test_a_sideways_phone_photo_reaches_the_model_upright(tmp_path: Path) -> None:
    stored = np.zeros((24, 48, 3), np.uint8)  # stored 48 wide, 24 high; shown 24 wide, 48 high
    stored[:, :12] = 255  # the stored left band: the top once shown
    path = save_with_orientation(Image.fromarray(stored), tmp_path / "phone.png", 6)
    item = load_input(path, 32)
    expected = fit_and_pad(np.rot90(stored, k=-1).astype(np.float32) / 255, 32)
    np.testing.assert_allclose(item.image.permute(1, 2, 0).numpy(), expected, atol=1e-6)


def test_alpha_box_is_in_the_upright_grid(tmp_path: Path) -> None:
    stored = np.zeros((20, 40, 4), np.uint8)
    stored[2:6, 30:38, 3] = 255  # opaque black at rows 2-5, columns 30-37 as stored; transparent elsewhere
    path = save_with_orientation(Image.fromarray(stored, "RGBA"), tmp_path / "cutout.png", 6)
    # shown turned clockwise: stored (row r, column c) lands at (row c, column H - 1 - r) with H = 20
    np.testing.assert_array_equal(alpha_bbox(path), [20 - 1 - 5, 30, 20 - 1 - 2, 37])
    raw = read_input(path)
    assert raw.image.shape == (40, 20, 3)
    x1, y1, x2, y2 = raw.bbox.astype(int)
    assert (raw.image[y1 : y2 + 1, x1 : x2 + 1] < 1).all()  # the box holds the opaque (black) pixels


def test_non_finite_input_is_a_bad_image(tmp_path: Path) -> None:
    path = tmp_path / "nan.tif"
    Image.fromarray(np.full((8, 8), np.nan, np.float32), "F").save(path)
    with pytest.raises(ImageLoadError, match=r"nan.tif: pixel values are NaN or infinite"):
        load_input(path, 32)


@pytest.mark.parametrize("mode", ["RGB", "L"])
def test_a_transparent_colour_key_crops_like_an_alpha_channel(tmp_path: Path, mode: str) -> None:
    stored = np.full((20, 30, 3), 255, np.uint8)
    stored[4:9, 10:20] = (200, 30, 30)  # the object; white, marked transparent by the PNG's tRNS chunk, elsewhere
    image = Image.fromarray(stored).convert(mode)
    key = (255, 255, 255) if mode == "RGB" else 255
    image.save(tmp_path / "keyed.png", transparency=key)
    np.testing.assert_array_equal(alpha_bbox(tmp_path / "keyed.png"), [10, 4, 19, 8])


@pytest.mark.parametrize(
    ("shape", "bbox", "spot"),
    [
        ((120, 200), None, (40, 50)),
        ((120, 200), None, (80, 150)),
        ((200, 120), None, (150, 30)),
        ((150, 150), (40, 30, 99, 79), (45, 90)),
        ((90, 160), (5, 10, 30, 70), (60, 12)),
    ],
)
def test_the_frame_locates_the_inputs_pixels_in_the_photo(tmp_path, shape, bbox, spot):
    from unicorn.io.images import RawInput, frame_input

    size, (H, W), (r, c) = 32, shape, spot
    image = np.zeros((H, W, 3), np.float32)
    image[r - 3 : r + 4, c - 3 : c + 4, 0] = 1.0  # a bright 7 x 7 square centred on pixel (r, c)
    framed = frame_input(RawInput(tmp_path / "x.png", image, None if bbox is None else np.array(bbox)), size)
    x, y, width, height = framed.frame
    # where the frame puts the spot's centre (pixel (r, c) spans [c, c + 1) x [r, r + 1)), in input pixels
    expected = ((r + 0.5 - y) / height * size - 0.5, (c + 0.5 - x) / width * size - 0.5)
    red = framed.image[0].double()
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    found = (float((red * rows).sum() / red.sum()), float((red * cols).sum() / red.sum()))  # the spot's centroid
    assert found == pytest.approx(expected, abs=0.25)
