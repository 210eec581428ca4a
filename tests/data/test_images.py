"""Image loading: mode conversion, bad files, decompression bombs, pixel limits, EXIF orientation."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.support.datasets import bomb_png, keyed_png16, save_with_orientation, swapped_rg_profile
from unicorn.data.images import (
    DEFAULT_MAX_IMAGE_BYTES,
    DEFAULT_MAX_IMAGE_PIXELS,
    MAX_IMAGE_BYTES_ENV,
    MAX_IMAGE_PIXELS_ENV,
    ImageLoadError,
    decode_image,
    decoded,
    load_image,
    load_image_and_alpha,
    load_mask,
    max_image_bytes,
    max_image_pixels,
    open_image,
    set_max_image_bytes,
    set_max_image_pixels,
)


def _save(path: Path, img: Image.Image) -> Path:
    img.save(path)
    return path


@pytest.mark.parametrize("mode", ["L", "RGBA", "P", "LA", "I;16", "RGB", "CMYK", "1"])
def test_load_image_converts_modes_to_rgb(tmp_path: Path, mode: str) -> None:
    rng = np.random.default_rng(0)
    rgb = Image.fromarray(rng.integers(0, 256, (12, 10, 3), dtype=np.uint8))
    if mode == "I;16":
        img = Image.fromarray((rng.integers(0, 65536, (12, 10))).astype(np.uint16))
        assert img.mode.startswith("I;16")
    else:
        img = rgb.convert(mode)
    suffix = ".jpg" if mode == "CMYK" else ".png"
    arr = load_image(_save(tmp_path / f"img{suffix}", img))
    assert arr.shape == (12, 10, 3) and arr.dtype == np.float32
    assert 0.0 <= arr.min() and arr.max() <= 1.0


def test_sixteen_bit_is_rescaled_not_clipped(tmp_path: Path) -> None:
    img = Image.fromarray(np.full((4, 4), 32768, dtype=np.uint16))
    arr = load_image(_save(tmp_path / "a.png", img))
    assert np.allclose(arr, 32768 / 65535, atol=1e-4)


def test_transparent_pixels_become_white(tmp_path: Path) -> None:
    rgba = np.zeros((4, 4, 4), dtype=np.uint8)
    rgba[..., 0] = 255
    rgba[:2, :, 3] = 255  # top half opaque red, bottom half transparent
    arr = load_image(_save(tmp_path / "a.png", Image.fromarray(rgba, "RGBA")))
    assert np.allclose(arr[0, 0], [1, 0, 0]) and np.allclose(arr[3, 0], [1, 1, 1])


@pytest.mark.parametrize("channels", [1, 3])
def test_a_16_bit_pngs_transparent_colour_becomes_white(tmp_path: Path, channels: int) -> None:
    samples = np.full((4, 6, channels), 1000, np.uint16)  # the key: transparent
    samples[1:3, 2:5] = (50000, 20000, 3000)[:channels]  # the object
    samples[3, 0] = (1200, 1100, 1000)[:channels]  # near the key, but opaque (8 bits: 1000 and 1200 are both 3 or 4)
    key = 1000 if channels == 1 else (1000, 1000, 1000)
    arr = load_image(keyed_png16(tmp_path / "keyed.png", samples.squeeze(-1) if channels == 1 else samples, key))
    transparent = (samples == 1000).all(axis=-1)
    np.testing.assert_array_equal(arr[transparent], 1.0)
    opaque = np.broadcast_to(samples[~transparent] / 65535, arr[~transparent].shape)
    np.testing.assert_allclose(arr[~transparent], opaque, atol=1 / 255)  # RGB: Pillow keeps the high byte
    assert (arr[3, 0] < 0.1).all()


@pytest.mark.parametrize("content", [b"", b"not an image at all", b"\x89PNG\r\n\x1a\n\x00\x00garbage"])
def test_corrupt_file_names_its_path(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "broken.png"
    path.write_bytes(content)
    with pytest.raises(ImageLoadError, match="broken.png"):
        load_image(path)
    with pytest.raises(ImageLoadError, match="key42"):
        decode_image(content, "key42")


def test_truncated_jpeg_is_reported(tmp_path: Path) -> None:
    good = _save(tmp_path / "good.jpg", Image.fromarray(np.zeros((64, 64, 3), np.uint8) + 90))
    bad = tmp_path / "truncated.jpg"
    bad.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ImageLoadError, match="truncated.jpg"):
        load_image(bad)


def test_missing_file_is_reported(tmp_path: Path) -> None:
    with pytest.raises(ImageLoadError, match="nope.png"):
        load_image(tmp_path / "nope.png")


def test_load_mask_any_mode(tmp_path: Path) -> None:
    m = np.zeros((5, 5), np.uint8)
    m[1:3, 1:4] = 255
    for mode in ("L", "RGB", "1"):
        arr = load_mask(_save(tmp_path / f"m_{mode}.png", Image.fromarray(m).convert(mode)))
        assert arr.shape == (5, 5) and set(np.unique(arr)) == {0.0, 1.0} and arr.sum() == 6


def test_load_mask_reads_colours_not_palette_indices_and_alpha_when_flat(tmp_path: Path) -> None:
    m = np.zeros((5, 5), np.uint8)
    m[1:3, 1:4] = 1
    palette = Image.fromarray(m, "P")
    palette.putpalette([255, 255, 255, 0, 0, 0])  # index 0 (the background) is white, index 1 (the shape) black
    np.testing.assert_array_equal(load_mask(_save(tmp_path / "palette.png", palette)), m == 0)
    green = np.zeros((5, 5, 3), np.uint8)
    green[m == 1] = (0, 255, 0)  # nothing in the first channel
    np.testing.assert_array_equal(load_mask(_save(tmp_path / "green.png", Image.fromarray(green))), m)
    drawn_in_alpha = np.full((5, 5, 4), 255, np.uint8)  # white throughout, the shape opaque
    drawn_in_alpha[..., 3] = m * 255
    np.testing.assert_array_equal(load_mask(_save(tmp_path / "alpha.png", Image.fromarray(drawn_in_alpha))), m)
    empty = np.zeros((5, 5, 4), np.uint8)
    empty[..., 3] = 255  # black and opaque throughout: an empty mask, whatever its channels
    assert not load_mask(_save(tmp_path / "empty.png", Image.fromarray(empty))).any()
    shaded = drawn_in_alpha.copy()
    shaded[..., :3] = (m * 255)[..., None]  # white shape on a black background, also transparent: the colours count
    np.testing.assert_array_equal(load_mask(_save(tmp_path / "shaded.png", Image.fromarray(shaded))), m)


@pytest.mark.parametrize("maxval", [65535, 1023])
def test_a_dark_sixteen_bit_pgm_is_not_read_as_eight_bit(tmp_path: Path, maxval: int) -> None:
    values = (np.arange(16).reshape(4, 4) * 10).astype(">u2")  # 0..150 of a 16-bit (or 10-bit) range, big-endian
    path = tmp_path / "dark.pgm"
    path.write_bytes(b"P5\n4 4\n%d\n" % maxval + values.tobytes())
    np.testing.assert_allclose(load_image(path)[..., 0], values / maxval, atol=1e-4)


def test_an_image_turned_upright_keeps_its_file_format(tmp_path: Path) -> None:
    # the format tells how an integer image's samples are scaled (a 16-bit PNG opened as mode I)
    path = save_with_orientation(Image.new("L", (6, 4)), tmp_path / "turned.png", 6)
    with open_image(path, path) as img:
        turned = decoded(img, path)
        assert turned.size == (4, 6) and turned.format == "PNG"


def test_decompression_bomb_is_a_bad_image(tmp_path: Path) -> None:
    path = bomb_png(tmp_path / "bomb.png")
    assert path.stat().st_size < 400
    with pytest.raises(ImageLoadError, match=r"20000x20000 = 400000000 pixels exceeds the limit") as info:
        load_image(path)
    assert "--max-image-pixels" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ImageLoadError, match="exceeds the limit"):
        decode_image(path.read_bytes(), "record-7")
    with pytest.raises(ImageLoadError, match="exceeds the limit"):
        load_mask(path)


def test_pixel_limit_can_be_raised_and_lowered(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, "")  # empty: the default; restored after the test
    assert max_image_pixels() == DEFAULT_MAX_IMAGE_PIXELS
    path = _save(tmp_path / "small.png", Image.new("RGB", (20, 10)))
    set_max_image_pixels(199)
    assert os.environ[MAX_IMAGE_PIXELS_ENV] == "199"  # inherited by DataLoader workers
    with pytest.raises(ImageLoadError, match="200 pixels exceeds the limit of 199"):
        load_image(path)
    set_max_image_pixels(200)
    assert load_image(path).shape == (10, 20, 3)
    set_max_image_pixels(0)  # no limit: PIL's own bomb check is not in the way either
    assert max_image_pixels() is None
    with pytest.raises(ImageLoadError, match="bomb.png"):  # decodes the header, then fails on the short data
        load_image(bomb_png(tmp_path / "bomb.png", 3000, 3000))
    with pytest.raises(ValueError, match=">= 0"):
        set_max_image_pixels(-1)


def test_any_decode_failure_is_a_bad_image(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import struct

    path = _save(tmp_path / "ok.png", Image.new("RGB", (4, 4)))

    def broken_decoder(self):
        raise struct.error("unpack requires a buffer of 4 bytes")  # neither OSError nor ValueError

    monkeypatch.setattr(Image.Image, "load", broken_decoder)
    with pytest.raises(ImageLoadError, match=r"ok.png: error: unpack requires"):
        load_image(path)


def test_a_one_bit_bomb_within_the_pixel_limit_is_refused_by_its_decoded_bytes(tmp_path: Path) -> None:
    # 13000 x 13000 = 169e6 pixels, under the pixel limit; as float32 RGB 2.03e9 bytes, over the 1 GiB default
    path = bomb_png(tmp_path / "bits.png", 13000, 13000, one_bit=True)
    assert 13000 * 13000 < DEFAULT_MAX_IMAGE_PIXELS
    with pytest.raises(ImageLoadError, match=r"bits.png: 13000x13000 pixels decode to 2028000000 bytes") as info:
        load_image(path)
    assert "--max-image-bytes" in str(info.value) and MAX_IMAGE_BYTES_ENV in str(info.value)
    assert "\n" not in str(info.value)
    with pytest.raises(ImageLoadError, match="record-3: .*decode to 2028000000 bytes"):
        decode_image(path.read_bytes(), "record-3")


def test_byte_limit_counts_what_each_loader_returns(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(MAX_IMAGE_BYTES_ENV, "")  # empty: the default; restored after the test
    assert max_image_bytes() == DEFAULT_MAX_IMAGE_BYTES
    path = _save(tmp_path / "small.png", Image.new("1", (20, 10)))  # 1 bit per pixel on disk, 12 bytes loaded
    set_max_image_bytes(20 * 10 * 12 - 1)
    assert os.environ[MAX_IMAGE_BYTES_ENV] == "2399"  # inherited by DataLoader workers
    with pytest.raises(ImageLoadError, match="decode to 2400 bytes .12 per pixel., over the limit of 2399"):
        load_image(path)
    assert load_mask(path).shape == (10, 20)  # a mask is one float32 band: 800 bytes
    set_max_image_bytes(20 * 10 * 4 - 1)
    with pytest.raises(ImageLoadError, match="decode to 800 bytes .4 per pixel."):
        load_mask(path)
    set_max_image_bytes(20 * 10 * 12)
    assert load_image(path).shape == (10, 20, 3)
    set_max_image_bytes(0)
    assert max_image_bytes() is None
    with pytest.raises(ValueError, match=">= 0"):
        set_max_image_bytes(-1)
    monkeypatch.setenv(MAX_IMAGE_BYTES_ENV, "lots")
    with pytest.raises(ValueError, match="UNICORN_MAX_IMAGE_BYTES='lots' is not a number of bytes"):
        load_image(path)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_pixels_are_a_bad_image(tmp_path: Path, bad: float) -> None:
    values = np.full((6, 5), 0.5, np.float32)
    values[2, 3] = bad
    path = _save(tmp_path / "float.tif", Image.fromarray(values, "F"))
    for read in (load_image, load_mask, lambda p: decode_image(p.read_bytes(), str(p))):
        with pytest.raises(ImageLoadError, match=r"float.tif: pixel values are NaN or infinite"):
            read(path)
    finite = _save(tmp_path / "finite.tif", Image.fromarray(np.full((6, 5), 0.25, np.float32), "F"))
    np.testing.assert_allclose(load_image(finite), 0.25)


@pytest.mark.parametrize("low, high", [(0.0, 255.0), (-0.5, 0.5)])
def test_float_pixels_outside_the_unit_range_are_a_bad_image(tmp_path: Path, low: float, high: float) -> None:
    values = np.linspace(low, high, 30, dtype=np.float32).reshape(6, 5)  # a 0-255 float TIFF would clip to white
    path = _save(tmp_path / "float.tif", Image.fromarray(values, "F"))
    for read in (load_image, lambda p: decode_image(p.read_bytes(), str(p))):
        with pytest.raises(ImageLoadError, match=rf"float.tif: float pixel values span \[{low:g}, {high:g}\], not"):
            read(path)
    assert load_mask(path).sum() > 0  # a mask is thresholded at half its maximum, whatever the scale
    rounded = _save(
        tmp_path / "rounded.tif", Image.fromarray(np.linspace(-1e-4, 1 + 1e-4, 30, dtype=np.float32).reshape(6, 5), "F")
    )
    assert load_image(rounded).min() == 0.0 and load_image(rounded).max() == 1.0


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_exif_orientation_is_applied(tmp_path: Path, suffix: str) -> None:
    stored = np.zeros((10, 20, 3), np.uint8)  # 20 wide, 10 high as stored
    stored[:, :5] = 255  # a white band on the stored left: on the top once shown turned clockwise
    path = save_with_orientation(Image.fromarray(stored), tmp_path / f"phone{suffix}", 6)
    shown = np.rot90(stored, k=-1).astype(np.float32) / 255  # ImageOps.exif_transpose's reading of orientation 6
    tol = 0.1 if suffix == ".jpg" else 0.0
    for upright in (load_image(path), decode_image(path.read_bytes(), "phone")):
        assert upright.shape == (20, 10, 3)
        np.testing.assert_allclose(upright, shown, atol=tol)
    mask = load_mask(path)
    assert mask.shape == (20, 10) and mask[:5].all() and not mask[6:].any()
    np.testing.assert_allclose(load_image(path, exif_orientation=False), stored / 255, atol=tol)
    assert load_mask(path, exif_orientation=False).shape == (10, 20)


def test_damaged_exif_is_one_warning_naming_the_file(tmp_path: Path, monkeypatch) -> None:
    """A photo whose EXIF block is cut short (a tag's data past its end) is read upright by the orientation that
    survives; the decoder's unnamed complaints become one ImageMetadataWarning naming the file, once per file."""
    import warnings

    from unicorn.data import images

    stored = np.zeros((10, 20, 3), np.uint8)
    stored[:, :5] = 255
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: turn clockwise
    exif[0x010E] = "a description longer than what is left of the block" * 2
    path = tmp_path / "phone.jpg"
    Image.fromarray(stored).save(path, exif=exif.tobytes()[:-60])  # the description's data cut off
    monkeypatch.setattr(images, "_DAMAGED_WARNED", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            upright = load_image(path)
            assert upright.shape == (20, 10, 3) and upright[:5].mean() > 0.9  # the white band on top
        load_mask(path)
    assert [(w.category, w.filename) for w in caught] == [(images.ImageMetadataWarning, __file__)]
    assert str(caught[0].message).startswith(f"{path}: damaged metadata (Tag data larger than file")
    # a file read before is not named again; another is
    other = tmp_path / "other.jpg"
    other.write_bytes(path.read_bytes())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_image(path), load_image(other)
    assert [str(w.message).split(":")[0] for w in caught] == [str(other)]


def test_a_heic_photo_is_listed_and_read_through_pillow_heif(tmp_path: Path) -> None:
    pillow_heif = pytest.importorskip("pillow_heif")  # the heif extra (dev installs it)
    import subprocess
    import sys

    rows, cols = np.mgrid[0:48, 0:64]
    photo = np.stack([rows * 5, cols * 4, np.full_like(rows, 90)], axis=-1).astype(np.uint8)  # smooth: little loss
    pillow_heif.from_pillow(Image.fromarray(photo)).save(tmp_path / "IMG_0001.HEIC", quality=95)
    np.save(tmp_path / "photo.npy", photo)
    code = (  # a new process: nothing has registered pillow-heif's opener with Pillow yet
        "import numpy as np, pathlib\n"
        "from unicorn.data.folder import list_images\n"
        "from unicorn.data.images import load_image\n"
        f"root = pathlib.Path({str(tmp_path)!r})\n"
        "assert list_images(root) == [root / 'IMG_0001.HEIC'], list_images(root)\n"
        "arr = load_image(root / 'IMG_0001.HEIC')\n"
        "print(arr.shape, float(np.abs(arr - np.load(root / 'photo.npy') / 255).mean()))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    shape, error = proc.stdout.rsplit(")", 1)
    assert shape == "(48, 64, 3" and float(error) < 0.02


#: the first bytes of a HEIF and an AVIF file (an ISO base media file's ftyp box)
_ISO_HEADERS = {"heic": b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic", "avif": b"\x00\x00\x00\x18ftypavif"}


def test_without_pillow_heif_a_heic_photo_says_what_to_install(tmp_path: Path) -> None:
    import subprocess
    import sys

    path = tmp_path / "IMG_0002.heic"
    path.write_bytes(_ISO_HEADERS["heic"] + bytes(64))
    code = (
        "import sys; sys.modules['pillow_heif'] = None\n"  # as if not installed
        "from unicorn.data.images import load_image\n"
        f"load_image({str(path)!r})\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1] == (
        f"unicorn.data.images.ImageLoadError: cannot read image {path}: it is a HEIF/HEIC image (a phone's photo "
        "format), which needs pillow-heif: pip install pillow-heif (the heif extra), or convert it to JPEG"
    )


def test_an_avif_image_without_pillows_support_says_what_to_install(tmp_path: Path, monkeypatch) -> None:
    from PIL import features

    monkeypatch.setattr(features, "check", lambda feature: False)  # as Pillow before 11.3
    path = tmp_path / "photo.avif"
    path.write_bytes(_ISO_HEADERS["avif"] + bytes(64))
    with pytest.raises(ImageLoadError, match=r"photo.avif: it is an AVIF image, which Pillow reads from 11.3 "):
        load_image(path)
    (tmp_path / "other.avif").write_bytes(b"\x00\x00\x00\x18ftypqt  " + bytes(64))  # another ISO file: Pillow's error
    with pytest.raises(ImageLoadError, match=r"other.avif: UnidentifiedImageError: cannot identify image file"):
        load_image(tmp_path / "other.avif")


def test_colours_in_another_colour_profile_are_read_in_srgb(tmp_path: Path, monkeypatch) -> None:
    """An embedded ICC profile's colours (a phone's Display P3, Adobe RGB) are converted to sRGB, as viewers show
    them; an sRGB profile's are read as stored; a profile that cannot be used is one warning naming the file."""
    import warnings

    from PIL import ImageCms

    from unicorn.data import images

    rng = np.random.default_rng(0)
    stored = rng.integers(0, 256, (6, 8, 4), dtype=np.uint8)
    stored[..., 3] = 255
    stored[4:, :, 3] = 0  # transparent rows
    Image.fromarray(stored, "RGBA").save(tmp_path / "swapped.png", icc_profile=swapped_rg_profile())
    arr = load_image(tmp_path / "swapped.png")
    np.testing.assert_array_equal(arr[:4] * 255, stored[:4, :, [1, 0, 2]])  # red and green swapped, exactly
    np.testing.assert_array_equal(arr[4:], 1.0)  # the alpha kept: composited on white
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    Image.fromarray(stored[..., :3]).save(tmp_path / "srgb.png", icc_profile=srgb)
    np.testing.assert_array_equal(load_image(tmp_path / "srgb.png") * 255, stored[..., :3])
    Image.fromarray(stored[..., :3]).save(tmp_path / "damaged.png", icc_profile=b"not a colour profile")
    monkeypatch.setattr(images, "_DAMAGED_WARNED", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            np.testing.assert_array_equal(load_image(tmp_path / "damaged.png") * 255, stored[..., :3])
    assert [(w.category, w.filename) for w in caught] == [(images.ImageMetadataWarning, __file__)]
    assert str(caught[0].message).startswith(f"{tmp_path / 'damaged.png'}: its colour profile cannot be used (")


def _icc(space: bytes, pcs: bytes, device_class: bytes, tags: dict[bytes, bytes]) -> bytes:
    """A minimal ICC v2 profile of ``space`` (``b"GRAY"``, ``b"CMYK"``) with a description, D50 white and ``tags``,
    written byte by byte (Pillow's ImageCms makes only sRGB, Lab and XYZ profiles)."""
    import struct

    def xyz(*values: float) -> bytes:
        return b"".join(struct.pack(">i", round(v * 65536)) for v in values)

    name = b"test " + space + b"\0"
    desc = b"desc" + bytes(4) + struct.pack(">I", len(name)) + name + bytes(8 + 3 + 67)
    tags = {b"desc": desc, b"wtpt": b"XYZ " + bytes(4) + xyz(0.9642, 1.0, 0.8249), b"cprt": b"text\0\0\0\0-\0", **tags}
    offset, table, data = 128 + 4 + 12 * len(tags), b"", b""
    for signature, body in tags.items():
        body += bytes(-len(body) % 4)
        table, data = table + signature + struct.pack(">II", offset + len(data), len(body)), data + body
    header = struct.pack(">I4sI", offset + len(data), b"lcms", 0x02100000) + device_class + space + pcs + bytes(12)
    header += b"acsp" + bytes(28) + xyz(0.9642, 1.0, 0.8249) + bytes(48)
    return header + struct.pack(">I", len(tags)) + table + data


def _linear_grey_profile() -> bytes:
    """A grey profile whose levels are linear light (gamma 1): level v is sRGB's encoding of v."""
    return _icc(b"GRAY", b"XYZ ", b"mntr", {b"kTRC": b"curv" + bytes(4) + (1).to_bytes(4, "big") + b"\x01\x00"})


def _cmyk_profile() -> bytes:
    """A CMYK profile of neutral inks: lightness L* = 100 (1 - k) (1 - c / 2) (a lut8 of 2 points a channel)."""
    ramp = bytes(range(256))
    identity = b"".join((v << 16).to_bytes(4, "big") for v in (1, 0, 0, 0, 1, 0, 0, 0, 1))
    corners = [(c, k) for c in (0, 1) for _m in (0, 1) for _y in (0, 1) for k in (0, 1)]  # C varies slowest
    lab = b"".join(bytes([round(255 * (1 - k) * (1 - c / 2)), 128, 128]) for c, k in corners)
    return _icc(
        b"CMYK",
        b"Lab ",
        b"prtr",
        {b"A2B0": b"mft1" + bytes(4) + bytes([4, 3, 2, 0]) + identity + ramp * 4 + lab + ramp * 3},
    )


def _srgb_encoded(linear: np.ndarray | float) -> np.ndarray:
    """sRGB's encoding of linear light in [0, 1] (IEC 61966-2-1)."""
    linear = np.asarray(linear, np.float64)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def test_grey_cmyk_and_keyed_images_are_read_through_their_colour_profile(tmp_path: Path) -> None:
    """A grey, grey-and-alpha, palette or CMYK image's embedded profile is applied as an RGB image's is (a Photoshop
    CMYK JPEG's inks, a greyscale's tone curve), keeping its transparency; a profile of another space than the
    image's (an RGB photo's, which Pillow's convert("L") keeps) is not the image's: its levels are read as stored."""
    import warnings

    levels = np.array([[0, 64, 128, 255]], np.uint8)
    expected = _srgb_encoded(levels / 255)  # linear light, in sRGB
    Image.fromarray(levels).save(tmp_path / "grey.png", icc_profile=_linear_grey_profile())
    np.testing.assert_allclose(
        load_image(tmp_path / "grey.png")[0], np.repeat(expected[0, :, None], 3, 1), atol=1 / 255
    )
    # grey and alpha: the alpha kept (the transparent pixel white); a transparent grey level (tRNS) likewise
    alpha = np.array([[255, 255, 0, 255]], np.uint8)
    Image.fromarray(np.stack([levels, alpha], -1), "LA").save(tmp_path / "la.png", icc_profile=_linear_grey_profile())
    Image.fromarray(levels).save(tmp_path / "keyed.png", icc_profile=_linear_grey_profile(), transparency=128)
    for name in ("la.png", "keyed.png"):
        arr = load_image(tmp_path / name)[0, :, 0]
        np.testing.assert_allclose(arr, [expected[0, 0], expected[0, 1], 1.0, expected[0, 3]], atol=1 / 255)
    # an RGB image's transparent colour (tRNS) is kept through its profile's conversion
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[0, 0], rgb[1, 1] = (10, 20, 30), (200, 100, 0)
    Image.fromarray(rgb).save(tmp_path / "rgb.png", icc_profile=swapped_rg_profile(), transparency=(10, 20, 30))
    np.testing.assert_array_equal(
        load_image(tmp_path / "rgb.png") * 255, [[[255] * 3, [0] * 3], [[0] * 3, [100, 200, 0]]]
    )
    # a palette's colours, likewise
    palette = Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE)
    palette.save(tmp_path / "palette.png", icc_profile=swapped_rg_profile())
    np.testing.assert_array_equal(load_image(tmp_path / "palette.png") * 255, rgb[..., [1, 0, 2]])
    # CMYK, stored inverted as Photoshop does (Adobe's marker): no ink is white, cyan a mid grey, black ink black
    cmyk = Image.new("CMYK", (24, 8), (0, 0, 0, 0))
    cmyk.paste((255, 0, 0, 0), (8, 0, 16, 8))
    cmyk.paste((0, 0, 0, 255), (16, 0, 24, 8))
    cmyk.save(tmp_path / "press.jpg", quality=100, icc_profile=_cmyk_profile())
    mid = _srgb_encoded(((128 / 2.55 + 16) / 116) ** 3)  # L* = 50 as the lut8 stores it (128 of 255), in sRGB
    np.testing.assert_allclose(
        load_image(tmp_path / "press.jpg")[4, ::8], np.repeat([[1.0], [mid], [0.0]], 3, 1), atol=2 / 255
    )
    # a grey image with an RGB profile: as stored, and nothing to warn about
    Image.fromarray(levels).save(tmp_path / "converted.png", icc_profile=swapped_rg_profile())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(load_image(tmp_path / "converted.png")[0, :, 0] * 255, levels[0])


def test_a_16_bit_rgb_pngs_transparent_colour_is_matched_on_all_16_bits(tmp_path: Path) -> None:
    """Only the tRNS colour itself is transparent, not the colours sharing its high bytes (a dark shadow on a black
    key), whatever the rows' filters (Sub's differences span a pixel's 6 bytes)."""
    import struct
    import zlib

    samples = np.zeros((3, 4, 3), np.uint16)  # the key, black: transparent
    samples[1, 1:3] = (255, 255, 255)  # a shadow darker than 1/256: the key's high bytes, opaque
    samples[2, 0] = (0, 0, 1)
    samples[2, 3] = (51400, 25700, 0)  # a colour
    rows = samples.astype(">u2").reshape(3, -1).view(np.uint8).astype(np.int16)
    sub = rows.copy()
    sub[:, 6:] = (rows[:, 6:] - rows[:, :-6]) % 256  # filter 1 (Sub): each byte less the pixel before's
    data = b"".join(b"\x01" + row.astype(np.uint8).tobytes() for row in sub)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    path = tmp_path / "keyed.png"
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", 4, 3, 16, 2, 0, 0, 0))
        + chunk(b"tRNS", struct.pack(">HHH", 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(data))
        + chunk(b"IEND", b"")
    )
    transparent = (samples == 0).all(axis=-1)
    for rgb, alpha in [load_image_and_alpha(path), (decode_image(path.read_bytes(), "keyed"), None)]:
        np.testing.assert_array_equal(rgb[transparent], 1.0)
        np.testing.assert_allclose(rgb[~transparent], samples[~transparent] / 65535, atol=1 / 255)  # 8 bits kept
        if alpha is not None:
            np.testing.assert_array_equal(alpha, ~transparent)
