"""Image loading shared by the loaders (the crop / pad / resize / flip steps: :mod:`unicorn.data.framing`).

Arrays are numpy ``(H, W, 3)`` float32 in [0, 1] until :func:`to_chw_tensor` turns them into ``(C, H, W)``
tensors. Every decode goes through :func:`open_image` and :func:`decoded`, so every loader (:func:`load_image`,
:func:`decode_image`, :func:`load_mask`) treats these the same way: any failure (truncated, not an image, an
unknown format) is an :class:`ImageLoadError` naming the file, and so are

- an image of more than :func:`max_image_pixels` pixels, or whose decoded array (width x height x bands x bytes
  per band of what the loader returns: 12 bytes per pixel for float32 RGB, 4 for a float32 mask) exceeds
  :func:`max_image_bytes`, refused from its header before it is decoded (a decompression bomb: a 20 KB 1-bit PNG
  of 13000 x 13000 pixels decodes to 2 GB of float32 RGB). Raise the limits with ``UNICORN_MAX_IMAGE_PIXELS`` /
  ``UNICORN_MAX_IMAGE_BYTES``, ``dataset.max_image_pixels`` / ``dataset.max_image_bytes`` or the tools'
  ``--max-image-pixels`` / ``--max-image-bytes``;
- an image whose pixels decode to NaN or infinite values (a float TIFF).

Images are read in sRGB: colours an embedded ICC profile puts in another space (a phone's Display P3, Adobe RGB, a
CMYK JPEG's press inks, a greyscale's tone curve) are converted, as image viewers show them (a profile of another
colour space than the image's: left out; a profile that cannot be used: one :class:`ImageMetadataWarning`, the
colours as stored).

A 16-bit PNG's transparent colour (``tRNS``) is matched on its 16 bits; Pillow reads a 16-bit RGB PNG's colours at
8 bits (16-bit grey ones keep their 16).

HEIF / HEIC images (phones' photos) are read through pillow-heif where it is installed (the ``heif`` extra,
:func:`heif_support`); without it, such an image's error says how to read it. AVIF images need Pillow 11.3 or later.

EXIF orientation is applied (as ``PIL.ImageOps.exif_transpose``: a phone photo stored sideways with orientation 6
is returned upright) unless the loader is asked for the stored pixels (``exif_orientation=False``), which
datasets whose annotations refer to the stored pixel grid need (:mod:`unicorn.data.annotated`).
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np
import PIL
import torch
from PIL import ExifTags, Image, ImageCms, ImageOps, UnidentifiedImageError, features

from unicorn.checks import check_limit, env_limit
from unicorn.errors import UnicornWarning, UserError

__all__ = [
    "DEFAULT_MAX_IMAGE_BYTES",
    "DEFAULT_MAX_IMAGE_PIXELS",
    "MAX_IMAGE_BYTES_ENV",
    "MAX_IMAGE_PIXELS_ENV",
    "MASK_BYTES_PER_PIXEL",
    "RGB_BYTES_PER_PIXEL",
    "DatasetError",
    "DatasetNotFoundError",
    "ImageLoadError",
    "ImageMetadataWarning",
    "check_image_size",
    "decode_image",
    "decoded",
    "has_transparency",
    "heif_support",
    "load_image",
    "load_image_and_alpha",
    "load_mask",
    "max_image_bytes",
    "max_image_pixels",
    "open_image",
    "read_text",
    "require",
    "set_max_image_bytes",
    "set_max_image_pixels",
    "to_chw_tensor",
    "transparency_alpha",
]


class ImageLoadError(UserError, RuntimeError):
    """An image file (or LMDB record) could not be read or decoded; the message names it."""

    #: how the message starts, before the path (subclasses for items that cannot be made say why)
    lead = "cannot read image"

    def __init__(self, path: str | os.PathLike, reason: str) -> None:
        self.path = str(path)
        super().__init__(f"{self.lead} {self.path}: {reason}")


class ImageMetadataWarning(UnicornWarning):
    """An image's metadata is damaged: its pixels are read, turned by what could be read of its EXIF orientation, or
    with their colours as stored where its colour profile cannot be used. One line naming the file, once per file and
    process (in place of the decoder's warnings, which name no file and come again at every read)."""


class DatasetError(UserError, ValueError):
    """A dataset that cannot be used as given: an unknown name, split or category, a malformed annotation file,
    no readable item (the message names it)."""


class DatasetNotFoundError(UserError, FileNotFoundError):
    """A dataset root or annotation file is missing; the message says where the data comes from."""

    def __init__(self, path: str | os.PathLike, what: str, hint: str) -> None:
        self.path = str(path)
        super().__init__(f"{what} not found at {self.path}. {hint}")


def read_text(path: str | os.PathLike) -> str:
    """The UTF-8 text of an annotation or list file, without the byte-order mark some editors write first.

    Raises:
        DatasetError: the file cannot be read, or is not UTF-8 (naming the line and byte).
    """
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        line = err.object[: err.start].count(b"\n") + 1
        raise DatasetError(f"line {line} of {path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise DatasetError(f"cannot read {path}: {err.strerror or err}") from None


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
#: decoded bytes above which an image is refused: 1 GiB, a float32 RGB image of about 89 megapixels (a 48 MP
#: phone photo takes 576 MB); the decode and conversion temporaries come on top
DEFAULT_MAX_IMAGE_BYTES = 1 << 30
#: environment variable holding the bytes limit (inherited by DataLoader workers); 0 means no limit
MAX_IMAGE_BYTES_ENV = "UNICORN_MAX_IMAGE_BYTES"
#: bytes per pixel of what the loaders return: float32 RGB images, float32 masks
RGB_BYTES_PER_PIXEL = 3 * 4
MASK_BYTES_PER_PIXEL = 4
#: how far outside [0, 1] a float image's values may lie (rounding) before the image is refused as of another scale
FLOAT_SLACK = 1e-3
#: file formats whose integer images (mode ``I``) hold 16-bit samples: PNG's 16-bit grey, and PGM with a maximum over
#: 255, which Pillow rescales to 0-65535
_SIXTEEN_BIT_FORMATS = ("PNG", "PPM")
_PIL_LOCK = threading.Lock()
_SRGB_PROFILE = ImageCms.createProfile("sRGB")
_DAMAGED_WARNED: set[str] = set()  # the files an ImageMetadataWarning has named


#: the brands of an ISO base media file (its bytes 8-12, after ``ftyp``) that hold HEIF stills, and AVIF's
_HEIF_BRANDS = (b"heic", b"heix", b"heim", b"heis", b"hevc", b"hevx", b"mif1", b"msf1")
_AVIF_BRANDS = (b"avif", b"avis")


@functools.cache
def heif_support() -> bool:
    """Whether HEIF / HEIC images can be read: pillow-heif is installed (the ``heif`` extra); the first call registers
    its opener with Pillow."""
    try:
        from pillow_heif import register_heif_opener
    except ImportError:
        return False
    register_heif_opener()
    return True


def _unreadable_format(source: str | os.PathLike | IO[bytes]) -> str | None:
    """What to do with an image Pillow could not identify whose format needs more than Pillow has, or None."""
    try:
        if isinstance(source, (str, os.PathLike)):
            with open(source, "rb") as f:
                head = f.read(12)
        else:
            start = source.tell()
            head = source.read(12)
            source.seek(start)
    except (OSError, ValueError):
        return None
    if head[4:8] != b"ftyp":
        return None
    if head[8:12] in _HEIF_BRANDS and not heif_support():
        return (
            "it is a HEIF/HEIC image (a phone's photo format), which needs pillow-heif: "
            "pip install pillow-heif (the heif extra), or convert it to JPEG"
        )
    if head[8:12] in _AVIF_BRANDS and not features.check("avif"):
        installed = PIL.__version__
        return f"it is an AVIF image, which Pillow reads from 11.3 (installed: {installed}): pip install -U pillow"
    return None


class ImageLimitError(UserError, ValueError):
    """An invalid image pixel or byte limit."""


def _read_limit(env: str, default: int, unit: str) -> int | None:
    return env_limit(env, default, unit)


def _write_limit(env: str, limit: int | None, what: str) -> None:
    if limit is not None and limit < 0:
        raise ImageLimitError(f"the image {what} limit must be >= 0 (0: none), got {limit}")
    os.environ[env] = str(int(limit or 0))


def max_image_pixels() -> int | None:
    """The current limit on pixels per image (None: no limit); see :func:`set_max_image_pixels`."""
    return _read_limit(MAX_IMAGE_PIXELS_ENV, DEFAULT_MAX_IMAGE_PIXELS, "pixels")


def set_max_image_pixels(limit: int | None) -> None:
    """Set the limit on pixels per image for this process and its children (None or 0: no limit).

    Raises:
        ImageLimitError: a negative limit.
    """
    _write_limit(MAX_IMAGE_PIXELS_ENV, limit, "pixel")


def max_image_bytes() -> int | None:
    """The current limit on the decoded bytes of an image (None: no limit); see :func:`set_max_image_bytes`."""
    return _read_limit(MAX_IMAGE_BYTES_ENV, DEFAULT_MAX_IMAGE_BYTES, "bytes")


def set_max_image_bytes(limit: int | None) -> None:
    """Set the limit on decoded bytes per image (width x height x bands x bytes per band of the array a loader
    returns) for this process and its children (None or 0: no limit).

    Raises:
        ImageLimitError: a negative limit.
    """
    _write_limit(MAX_IMAGE_BYTES_ENV, limit, "byte")


def check_image_size(setting: str, what: str, side: int, channels: int = 3, count: int = 1) -> None:
    """Refuse images a command would make (training images, texture maps, pictures, turntable frames) that the
    image limits would refuse to read, before they are allocated: ``count`` square images of ``side`` pixels and
    ``channels`` float32 channels, each above :func:`max_image_pixels` pixels, or together above
    :func:`max_image_bytes` bytes.

    Raises:
        unicorn.checks.SizeLimitError: the message names ``setting``, the size and the limit's variable.
    """
    pixels, source = side * side, f"{MAX_IMAGE_PIXELS_ENV}; 0: no limit"
    check_limit(setting, f"{what} of {side} x {side}", pixels, max_image_pixels(), "pixels", source)
    nbytes, source = count * pixels * channels * 4, f"{MAX_IMAGE_BYTES_ENV}; 0: no limit"
    what = f"{what}: {count} x {channels} x {side} x {side} float32"
    check_limit(setting, what, nbytes, max_image_bytes(), "bytes", source)


@contextlib.contextmanager
def open_image(
    source: str | os.PathLike | IO[bytes], name: str | os.PathLike, bytes_per_pixel: int = RGB_BYTES_PER_PIXEL
) -> Iterator[Image.Image]:
    """``PIL.Image.open`` with the pixel and byte limits and one error type; ``name`` is used in errors.

    Args:
        source: file path or binary file object.
        name: what errors call the image.
        bytes_per_pixel: bytes per pixel of the array the caller makes of the image (bands x bytes per band
            after its conversion: :data:`RGB_BYTES_PER_PIXEL`, :data:`MASK_BYTES_PER_PIXEL`), for the byte limit.

    Yields the opened (not yet loaded) image. Any exception while opening or inside the block becomes an
    :class:`ImageLoadError` naming ``name``.
    """
    pixel_limit, byte_limit = max_image_pixels(), max_image_bytes()
    try:
        with _PIL_LOCK, warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")  # the decoder's complaints about the header's metadata, said below
            # PIL's global bomb check is replaced by the header checks below (its limit is not ours)
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                heif_support()  # registers the HEIF opener where pillow-heif is installed
                img = Image.open(source)  # reads the header only
            finally:
                Image.MAX_IMAGE_PIXELS = saved
        _report_damaged_metadata(name, caught, stacklevel=5)  # past contextlib: the loader's caller
        with img:
            pixels = img.width * img.height
            if pixel_limit is not None and pixels > pixel_limit:
                raise ImageLoadError(
                    name,
                    f"{img.width}x{img.height} = {pixels} pixels exceeds the limit of {pixel_limit} (a decompression "
                    f"bomb?); if the image is genuine raise the limit with --max-image-pixels, "
                    f"dataset.max_image_pixels or {MAX_IMAGE_PIXELS_ENV}",
                )
            size = pixels * bytes_per_pixel
            if byte_limit is not None and size > byte_limit:
                raise ImageLoadError(
                    name,
                    f"{img.width}x{img.height} pixels decode to {size} bytes ({bytes_per_pixel} per pixel), over the "
                    f"limit of {byte_limit} (a decompression bomb?); if the image is genuine raise the limit with "
                    f"--max-image-bytes, dataset.max_image_bytes or {MAX_IMAGE_BYTES_ENV}",
                )
            yield img
    except ImageLoadError:
        raise
    except Exception as err:  # PIL raises many kinds on bad files (OSError, SyntaxError, struct.error, ...)
        unreadable = _unreadable_format(source) if isinstance(err, UnidentifiedImageError) else None
        raise ImageLoadError(name, unreadable or f"{type(err).__name__}: {' '.join(str(err).split())}") from err


def decoded(img: Image.Image, name: str | os.PathLike, exif_orientation: bool = True) -> Image.Image:
    """Decode an image from :func:`open_image` the one way every loader does (call it inside that block).

    Loads the pixels, refuses non-finite ones (float images: a NaN TIFF is a bad image, not an image of NaNs),
    and turns the image upright by its EXIF orientation (``PIL.ImageOps.exif_transpose``) unless
    ``exif_orientation`` is False.

    Raises:
        ImageLoadError: non-finite pixel values.
    """
    key = img.info.get("transparency")
    keyed_16_bit = (
        img.format == "PNG"
        and img.mode == "RGB"
        and isinstance(key, tuple)
        and any(str(tile.args).endswith(";16B") for tile in img.tile)
    )
    low = _low_bytes(img) if keyed_16_bit else None  # read before load, which clears the tiles
    img.load()
    if low is not None:
        # Pillow keeps each 16-bit sample's high byte: the tRNS colour is matched on all 16 bits, as an alpha channel
        samples = np.asarray(img).astype(np.uint16) << 8 | low
        opaque = (samples != np.asarray(key, np.uint16)).any(axis=-1)
        del img.info["transparency"]
        img.putalpha(Image.fromarray(opaque.astype(np.uint8) * 255))
    if img.mode == "F" and not np.isfinite(np.asarray(img)).all():  # the one float mode; others are integers
        raise ImageLoadError(name, "pixel values are NaN or infinite")
    if not exif_orientation:
        return img
    with _PIL_LOCK, warnings.catch_warnings(record=True) as damaged:  # the filters are global: one thread at a time
        warnings.simplefilter("always")  # every decoder complaint is caught here, none shown as it is
        if img.getexif().get(ExifTags.Base.Orientation, 1) != 1:
            turned = ImageOps.exif_transpose(img)  # a copy: only made when there is something to turn
            turned.format = img.format  # the copy keeps the file's format, which tells how its samples are scaled
            img = turned
    _report_damaged_metadata(name, damaged, stacklevel=4)  # the loader's caller
    return img


def _low_bytes(img: Image.Image) -> np.ndarray:
    """(H, W, 3) uint8 low bytes of the samples of a 16-bit RGB PNG not yet loaded, whose high bytes Pillow reads (its
    ``RGB;16B`` tiles): the file decoded a second time, each sample's other byte kept (``RGB;16L``)."""
    start = img.fp.tell()
    img.fp.seek(0)  # the loaders open files and bytes from their start
    data = img.fp.read()
    img.fp.seek(start)
    with _PIL_LOCK, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # said when the image was opened
        saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # the limits were checked from the header
        try:
            twin = Image.open(io.BytesIO(data), formats=["PNG"])
        finally:
            Image.MAX_IMAGE_PIXELS = saved
    with twin:
        twin.tile = [tile._replace(args=tile.args[:-1] + "L") for tile in twin.tile]
        twin.load()
        return np.asarray(twin)


def _report_damaged_metadata(name: str | os.PathLike, caught: list[warnings.WarningMessage], stacklevel: int) -> None:
    """One :class:`ImageMetadataWarning` naming ``name`` for the decoder's warnings ``caught`` reading it (none if
    nothing was caught or the file was named before)."""
    if caught:
        first = " ".join(str(caught[0].message).split())
        message = f"damaged metadata ({first}); the pixels are read, turned by the orientation that could be read"
        _warn_once(name, message, stacklevel)


def _warn_once(name: str | os.PathLike, message: str, stacklevel: int) -> None:
    """One :class:`ImageMetadataWarning` ``"<name>: <message>"``, unless the file was named before."""
    if str(name) in _DAMAGED_WARNED:
        return
    _DAMAGED_WARNED.add(str(name))
    warnings.warn(f"{name}: {message}", ImageMetadataWarning, stacklevel=stacklevel + 1)


#: the modes whose colours an embedded ICC profile converts to sRGB: the colour space of the profiles that describe
#: such an image (ICC's signature), and the mode the image becomes
_MANAGED_MODES = {
    "RGB": ("RGB", "RGB"),
    "RGBA": ("RGB", "RGBA"),
    "CMYK": ("CMYK", "RGB"),  # a printing press's inks (Photoshop's CMYK JPEGs)
    "L": ("GRAY", "RGB"),  # a greyscale's tone curve (Photoshop's "Dot Gain 20%")
    "LA": ("GRAY", "RGBA"),
}


@functools.lru_cache(maxsize=32)
def _srgb_transform(icc: bytes, mode: str) -> ImageCms.ImageCmsTransform | None:
    """The transform from an ICC profile's colours to sRGB for images of ``mode`` (a key of :data:`_MANAGED_MODES`,
    ``LA`` excepted: its grey band is converted as ``L``); None for an sRGB profile (read as stored: most photos', and
    the conversion costs about as much as decoding a JPEG), or for a profile of another colour space than the
    image's, which does not describe its pixels (an RGB photo's profile that Pillow's ``convert("L")`` keeps)."""
    source = ImageCms.ImageCmsProfile(io.BytesIO(icc))
    space, out_mode = _MANAGED_MODES[mode]
    if "srgb" in ImageCms.getProfileDescription(source).lower() or source.profile.xcolor_space.strip() != space:
        return None
    return ImageCms.buildTransform(source, _SRGB_PROFILE, mode, out_mode)


def _in_srgb(img: Image.Image, name: str | os.PathLike) -> Image.Image:
    """The image with its colours in sRGB where its embedded ICC profile puts them in another space (a phone's
    Display P3, Adobe RGB, a CMYK press's inks, a greyscale's tone curve), as image viewers show them: RGB, or RGBA
    for an image with transparency. As stored without a profile, with an sRGB one, with one of another colour space
    than the image's, or with one that cannot be used (an :class:`ImageMetadataWarning`).
    """
    icc = img.info.get("icc_profile")
    if not icc or img.mode not in (*_MANAGED_MODES, "P"):
        return img
    mode = img.mode  # what LittleCMS converts: a palette's colours, a transparent colour made an alpha channel
    if mode == "P":
        mode = "RGBA" if has_transparency(img) else "RGB"
    elif mode in ("RGB", "L") and has_transparency(img):
        mode += "A"
    try:
        transform = _srgb_transform(bytes(icc), "L" if mode == "LA" else mode)
    except (OSError, ValueError, ImageCms.PyCMSError) as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        _warn_once(name, f"its colour profile cannot be used ({reason}); its colours are read as stored", 4)
        return img
    if transform is None:
        return img
    img = img.convert(mode)
    if mode == "LA":  # LittleCMS would drop the alpha of grey and alpha: the grey is converted alone
        converted = ImageCms.applyTransform(img.getchannel("L"), transform)
        converted.putalpha(img.getchannel("A"))
        return converted
    return ImageCms.applyTransform(img, transform)


def _pil_to_rgb(img: Image.Image, name: str | os.PathLike) -> np.ndarray:
    """Any PIL mode to an (H, W, 3) float32 RGB array in [0, 1], in sRGB (:func:`_in_srgb`).

    Raises:
        ImageLoadError: a float image (mode ``F``) with values outside [0, 1], whose scale cannot be told (0-255,
            0-65535, physical units).
    """
    img = _in_srgb(img, name)
    if img.mode in _WIDE_GREY_MODES:
        # 16-bit (or 32-bit int) grayscale: PIL's convert('L') clips instead of rescaling
        arr = np.asarray(img, dtype=np.float64)
        sixteen_bit = img.mode.startswith("I;16") or img.format in _SIXTEEN_BIT_FORMATS or arr.max() > 255
        peak = 65535.0 if sixteen_bit else 255.0  # a dark 16-bit image is not an 8-bit one
        gray = np.clip(arr / peak, 0.0, 1.0).astype(np.float32)
        alpha = transparency_alpha(img)
        if alpha is not None:  # composite on white, as below
            gray = gray * alpha + (1.0 - alpha)
        return np.repeat(gray[..., None], 3, axis=-1)
    if img.mode == "F":
        gray = np.asarray(img, dtype=np.float32)
        low, high = (float(gray.min()), float(gray.max())) if gray.size else (0.0, 0.0)
        if low < -FLOAT_SLACK or high > 1 + FLOAT_SLACK:  # clipped, 0-255 values would read as an all-white image
            raise ImageLoadError(
                name,
                f"float pixel values span [{low:g}, {high:g}], not [0, 1]: save the image with 8 or 16 bits per "
                "channel, or as floats scaled to [0, 1]",
            )
        gray = np.clip(gray, 0.0, 1.0)
        return np.repeat(gray[..., None], 3, axis=-1)
    if has_transparency(img):
        # composite transparent pixels on white, the NMR / ShapeNet background
        rgba = np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0
        alpha = rgba[..., 3:]
        return rgba[..., :3] * alpha + (1.0 - alpha)
    rgb = np.asarray(img if img.mode == "RGB" else img.convert("RGB"), dtype=np.float32)  # a new array
    rgb /= 255.0
    return rgb


#: PIL's modes of one band of integers wider than 8 bits (16-bit grey PNGs read as ``I;16``)
_WIDE_GREY_MODES = ("I", "I;16", "I;16B", "I;16L", "I;16N")


def has_transparency(img: Image.Image) -> bool:
    """Whether a PIL image has transparent pixels to read: an alpha channel, or a palette, RGB or grey image with a
    transparent entry or colour (a PNG's ``tRNS`` chunk, a GIF's transparent index)."""
    keyed = ("P", "RGB", "L", *_WIDE_GREY_MODES)
    return img.mode in ("RGBA", "LA", "PA") or (img.mode in keyed and "transparency" in img.info)


def transparency_alpha(img: Image.Image) -> np.ndarray | None:
    """(H, W) float32 opacity in [0, 1] of a decoded image (:func:`decoded`), or None without transparency.

    A 16-bit grey image's ``tRNS`` grey level is matched here: PIL's ``convert("RGBA")`` leaves such an image opaque.
    """
    if not has_transparency(img):
        return None
    if img.mode in _WIDE_GREY_MODES:
        return (np.asarray(img) != img.info["transparency"]).astype(np.float32)
    return np.asarray(img.convert("RGBA"))[..., 3].astype(np.float32) / 255.0


def load_image(path: str | os.PathLike, exif_orientation: bool = True) -> np.ndarray:
    """Read an image file as RGB, upright by its EXIF orientation unless ``exif_orientation`` is False.

    Grayscale, palette, RGBA (composited on white), CMYK and 16-bit images are converted; colours in another space
    than sRGB by their embedded ICC profile (a phone's Display P3, Adobe RGB, CMYK inks) are converted to sRGB.

    Args:
        path: image file.
        exif_orientation: apply the EXIF orientation tag; False returns the stored pixel grid.

    Returns:
        (H, W, 3) float32 array in [0, 1].

    Raises:
        ImageLoadError: if the file is missing, truncated, not an image, over the limits or not finite.
    """
    with open_image(path, path) as img:
        return _pil_to_rgb(decoded(img, path, exif_orientation), path)


def load_image_and_alpha(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`load_image` (upright) and :func:`transparency_alpha` of one image file, decoded once.

    Returns:
        (H, W, 3) float32 RGB in [0, 1] (transparent pixels composited on white) and the (H, W) float32 opacity, or
        None for an image without transparency.
    """
    with open_image(path, path) as img:
        img = decoded(img, path)
        return _pil_to_rgb(img, path), transparency_alpha(img)


def decode_image(data: bytes, name: str, exif_orientation: bool = True) -> np.ndarray:
    """Decode encoded image bytes (e.g. an LMDB value) like :func:`load_image`; ``name`` is used in errors."""
    with open_image(io.BytesIO(data), name) as img:
        return _pil_to_rgb(decoded(img, name, exif_orientation), name)


def load_mask(path: str | os.PathLike, exif_orientation: bool = True) -> np.ndarray:
    """Read a mask image as an (H, W) float32 array in {0, 1}, oriented as :func:`load_image` orients its image.

    The mask is the image's grey level (colour and palette images by their luminance, PIL's ``convert("L")``), or
    its alpha channel where an image of one colour throughout has a varying one, thresholded at half its maximum.
    """
    with open_image(path, path, MASK_BYTES_PER_PIXEL) as img:
        arr = _mask_levels(decoded(img, path, exif_orientation))
    return (arr > arr.max() / 2 if arr.max() > 0 else arr > 0).astype(np.float32)


def _mask_levels(img: Image.Image) -> np.ndarray:
    """(H, W) levels of a mask image, before thresholding."""
    if img.mode == "F" or img.mode in _WIDE_GREY_MODES:
        levels = np.asarray(img)  # one band of floats or wide integers, which convert("L") would clip
    else:
        levels = np.asarray(img.convert("L"))  # a palette image's colours, not its palette indices
    if levels.min() == levels.max():
        alpha = transparency_alpha(img)
        if alpha is not None and alpha.min() < alpha.max():  # the shape is drawn in the alpha channel alone
            return alpha
    return levels


def to_chw_tensor(arr: np.ndarray) -> torch.Tensor:
    """(H, W, C) or (H, W) array to a contiguous float32 tensor (C, H, W) / (1, H, W)."""
    if arr.ndim == 2:
        arr = arr[..., None]
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1), dtype=np.float32))
