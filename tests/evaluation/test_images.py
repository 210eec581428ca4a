"""User images: finding them, framing them like the training data."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.support.evaluation import write_inputs
from unicorn.data.images import ImageLoadError, load_image
from unicorn.errors import UserError
from unicorn.io import alpha_bbox, collect_inputs, load_input, preprocess


def test_collect_inputs(tmp_path: Path) -> None:
    files = write_inputs(tmp_path / "in")
    (tmp_path / "in" / "notes.txt").write_text("not an image")
    assert collect_inputs([tmp_path / "in"]) == sorted(files.values())
    assert collect_inputs([files["photo"], tmp_path / "in"])[0] == files["photo"]
    # one path on its own is one input, not its characters ("/" among them: the whole file system)
    assert collect_inputs(str(tmp_path / "in")) == collect_inputs(tmp_path / "in") == sorted(files.values())
    for raw in (str(tmp_path / "in").encode(), [str(tmp_path / "in").encode()]):
        with pytest.raises(TypeError, match="^collect_inputs takes paths as str or os.PathLike, not bytes"):
            collect_inputs(raw)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no images"):
        collect_inputs([tmp_path / "empty"])
    with pytest.raises(FileNotFoundError, match="input not found"):
        collect_inputs([tmp_path / "nope.png"])
    # a file reached twice is read once: under its own name where another is a link to it (sorted first here)
    (tmp_path / "in" / "a_link.png").symlink_to(files["photo"])
    assert collect_inputs([tmp_path / "in"]) == sorted(files.values())
    assert collect_inputs([tmp_path / "in" / "a_link.png", files["photo"]]) == [files["photo"]]
    assert collect_inputs([files["photo"], files["photo"]]) == [files["photo"]]
    os.mkfifo(tmp_path / "pipe.png")  # exists, but reading it would wait for a writer
    with pytest.raises(UserError, match=r"pipe\.png is not an image file or a folder \(a device, a pipe"):
        collect_inputs([tmp_path / "pipe.png"])


@pytest.mark.parametrize("size", [0, -3, "32", 32.0, True])
def test_a_size_that_is_not_a_positive_int_is_named(tmp_path: Path, size: object) -> None:
    files = write_inputs(tmp_path)
    with pytest.raises(
        ValueError, match=rf"^size must be a positive int \(the model's input side in pixels\), got {size!r}$"
    ):
        load_input(files["photo"], size)


def test_alpha_cutout_is_centred(tmp_path: Path) -> None:
    files = write_inputs(tmp_path)
    assert alpha_bbox(files["photo"]) is None
    np.testing.assert_array_equal(alpha_bbox(files["cutout"]), [50, 8, 83, 29])
    item = load_input(files["cutout"], 32)
    assert item.cropped and item.image.shape == (3, 32, 32)
    red = (item.image[0] > 0.6) & (item.image[1] < 0.4)  # (32, 32) object pixels
    rows, cols = np.nonzero(red.numpy())
    assert abs(rows.mean() - 15.5) < 1.5 and abs(cols.mean() - 15.5) < 1.5  # centred
    assert 0.5 < (cols.max() - cols.min() + 1) / 32 < 0.95  # fills most of the frame, with a margin
    assert float(item.image[:, 0, 0].min()) > 0.95  # transparent pixels became white


def _pattern(height: int, width: int) -> np.ndarray:
    """An (H, W, 3) uint8 image whose every pixel is different: red follows the column, green the row."""
    rows, cols = np.mgrid[0:height, 0:width]
    return np.stack([cols * 7 + 3, rows * 11 + 5, (rows * width + cols) % 251], axis=-1).astype(np.uint8)


@pytest.mark.parametrize("landscape", [True, False])
def test_opaque_image_is_fit_and_padded(tmp_path: Path, landscape: bool) -> None:
    """Where a framed opaque image lands, against its pixels placed by hand: centred, its border repeated."""
    # the longer side is the model's size: no resampling, the pixels are placed as they are
    arr = _pattern(19, 32) if landscape else _pattern(32, 19)
    Image.fromarray(arr).save(tmp_path / "pattern.png")
    item = load_input(tmp_path / "pattern.png", 32)
    assert not item.cropped
    got = item.image.permute(1, 2, 0).numpy()
    want = arr.astype(np.float64) / 255
    if not landscape:  # a portrait image is the landscape case turned: its padding columns are rows
        got, want = got.transpose(1, 0, 2), want.transpose(1, 0, 2)
    # 32 - 19 = 13 lines of padding: 6 before, 7 after
    np.testing.assert_allclose(got[6:25], want, atol=1e-6)
    np.testing.assert_allclose(got[:6], np.broadcast_to(want[0], (6, 32, 3)), atol=1e-6)
    np.testing.assert_allclose(got[25:], np.broadcast_to(want[-1], (7, 32, 3)), atol=1e-6)
    # the frame: the image's own pixels, 6 lines beyond its edge, 32 wide, as the photo spans 32 x 19
    frame = (0.0, -6.0, 32.0, 32.0) if landscape else (-6.0, 0.0, 32.0, 32.0)
    assert item.frame == pytest.approx(frame)

    # twice as large: halved first, so each block of colour keeps its place (away from its edges)
    blocks = np.zeros((38, 64, 3), dtype=np.uint8)
    blocks[:, :32] = (255, 0, 0)
    blocks[:, 32:] = (0, 0, 255)
    blocks[:10, :] = (0, 255, 0)  # a band along the top edge, which the padding repeats upwards
    Image.fromarray(blocks).save(tmp_path / "blocks.png")
    framed = load_input(tmp_path / "blocks.png", 32).image.permute(1, 2, 0).numpy()  # 32 x 19 at rows 6..24
    np.testing.assert_allclose(framed[:8], np.broadcast_to([0.0, 1.0, 0.0], (8, 32, 3)), atol=1e-6)  # band, above
    np.testing.assert_allclose(framed[12:32, :14], np.broadcast_to([1.0, 0.0, 0.0], (20, 14, 3)), atol=1e-6)
    np.testing.assert_allclose(framed[12:32, 18:], np.broadcast_to([0.0, 0.0, 1.0], (20, 14, 3)), atol=1e-6)
    np.testing.assert_allclose(framed[25:], np.broadcast_to(framed[24], (7, 32, 3)), atol=0)  # the bottom line
    boxed = preprocess(load_image(tmp_path / "pattern.png"), 16, bbox=(10, 5, 29, 24), padding=0.0)
    assert boxed.shape == (16, 16, 3)


def test_unreadable_image(tmp_path: Path) -> None:
    (tmp_path / "bad.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ImageLoadError, match="bad.png"):
        load_input(tmp_path / "bad.png", 32)
    Image.new("RGB", (4, 4)).save(tmp_path / "ok.png")
    assert load_input(tmp_path / "ok.png", 8).image.shape == (3, 8, 8)
