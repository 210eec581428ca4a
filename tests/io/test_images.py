"""User images for unicorn-reconstruct: orientation, and the checks every loader shares."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.support.datasets import keyed_png16, save_with_orientation
from unicorn.data.framing import fit_and_pad
from unicorn.data.images import ImageLoadError
from unicorn.io import alpha_bbox, load_input, preprocess, read_input
from unicorn.io.images import BoxError


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


def test_a_cutout_trimmed_to_its_object_is_framed_on_white(tmp_path: Path) -> None:
    """A cut-out whose object touches the image's edges (trimmed by the tool that cut it out): its square crop
    reaches beyond the image, which is white there (the cut-out's background), not its edge pixels repeated into
    streaks, whether its box is the alpha channel's or given; a photo's crop around a given box still repeats its
    border, as the training crops do."""
    rows, cols = np.mgrid[0:50, 0:100]
    inside = ((cols - 49.5) / 50) ** 2 + ((rows - 24.5) / 25) ** 2 <= 1  # an ellipse touching all four edges
    stored = np.zeros((50, 100, 4), np.uint8)
    stored[inside] = (200, 30, 30, 255)
    Image.fromarray(stored, "RGBA").save(tmp_path / "trimmed.png")
    item = load_input(tmp_path / "trimmed.png", 32)
    # the box grown by 10 %: x from -10 to 109, squared to y from -35 to 84: the image spans framed rows 9.3 to 22.7
    # and columns 2.7 to 29.3 (one framed pixel more left out: the resize's filter reaches over the edge)
    assert item.cropped and item.frame == pytest.approx((-10.0, -35.0, 120.0, 120.0))
    framed = item.image.permute(1, 2, 0).numpy()
    assert (framed[:8] == 1).all() and (framed[24:] == 1).all()  # above and below the image: white
    assert (framed[:, :1] == 1).all() and (framed[:, 31:] == 1).all()  # left and right of it: white
    np.testing.assert_allclose(framed[16, 16], [200 / 255, 30 / 255, 30 / 255], atol=1e-6)  # the object
    boxed = load_input(tmp_path / "trimmed.png", 32, bbox=(0, 0, 99, 49))  # the same box, given
    assert boxed.frame == item.frame and torch.equal(boxed.image, item.image)
    whole = load_input(tmp_path / "trimmed.png", 32, use_alpha=False).image  # fitted whole: white above and below
    assert (whole[:, :8] == 1).all() and (whole[:, 24:] == 1).all() and (whole[0, 16, :] < 1).any()
    Image.fromarray(stored[..., :3]).save(tmp_path / "photo.png")  # opaque: a photo on black
    photo = load_input(tmp_path / "photo.png", 32, bbox=(0, 0, 99, 49))  # a given box: the border repeated
    assert photo.frame == item.frame and not read_input(tmp_path / "photo.png", bbox=(0, 0, 99, 49)).cutout
    assert (photo.image[0, :8, 16] > 0.7).all()  # the object's top edge, repeated upwards


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


@pytest.mark.parametrize("channels", [1, 3])
def test_a_16_bit_transparent_colour_crops_like_an_alpha_channel(tmp_path: Path, channels: int) -> None:
    samples = np.full((20, 30, channels), 1000, np.uint16)  # near black: transparent
    samples[4:9, 10:20] = (40000, 9000, 1000)[:channels]  # the object; RGB: the key's value in one channel
    key = 1000 if channels == 1 else (1000, 1000, 1000)
    path = keyed_png16(tmp_path / "keyed.png", samples.squeeze(-1) if channels == 1 else samples, key)
    np.testing.assert_array_equal(alpha_bbox(path), [10, 4, 19, 8])
    assert read_input(path).cutout


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


@pytest.mark.parametrize("padding", ["0.1", None, True], ids=repr)
def test_a_padding_that_is_not_a_number_is_named(padding) -> None:
    image = np.zeros((8, 8, 3), dtype=np.float32)
    with pytest.raises(BoxError, match=rf"^padding {re.escape(repr(padding))}: must be a finite number in \[0, 10\]"):
        preprocess(image, 4, bbox=(1, 1, 5, 5), padding=padding)
