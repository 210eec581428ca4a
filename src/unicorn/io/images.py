"""User images for ``unicorn-reconstruct``: find them, read them and bring them to the training framing.

The framing is the training one (:mod:`unicorn.data.framing`):

- an image whose alpha channel cuts the object out (a PNG with transparency) is cropped to the square box around
  its opaque pixels grown by ``padding`` on every side (as the CUB / Pascal3D+ loaders crop around their boxes),
  composited on white and resized;
- a box given by the caller is used the same way;
- any other image (or a cut-out read without its alpha box) is resized so that its longer side is the model's size
  and padded to a square by replicating its border, centred (the image-folder / CompCars loaders' ``fit_and_pad``).

Where the frame reaches beyond an image with transparent pixels (a cut-out trimmed to its object), it is white
there, as its background is, not the image's border repeated.

Images are read upright by their EXIF orientation, as image viewers show them (a phone photo stored sideways with
orientation 6 reaches the model upright); a box given by the caller is in that displayed pixel grid.

The models reconstruct what fills the frame as their training images did: one object, centred, seen whole, filling
most of the square, on its natural background (or on white for models trained on ShapeNet renderings).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from unicorn.checks import is_whole
from unicorn.data.folder import IMAGE_EXTENSIONS, RECONSTRUCTIONS_RECORD, is_output_folder, list_images
from unicorn.data.framing import crop_box, fit_and_pad, fit_layout, pad_bbox, resize_image, square_bbox
from unicorn.data.images import (
    RGB_BYTES_PER_PIXEL,
    ImageLoadError,
    decoded,
    has_transparency,
    load_image_and_alpha,
    max_image_bytes,
    open_image,
    to_chw_tensor,
    transparency_alpha,
)
from unicorn.errors import UserError

__all__ = [
    "IMAGE_EXTENSIONS",
    "MAX_PADDING",
    "RECONSTRUCTIONS_RECORD",
    "BoxError",
    "InputImage",
    "RawInput",
    "alpha_bbox",
    "check_box",
    "check_padding",
    "collect_inputs",
    "frame_input",
    "load_input",
    "preprocess",
    "read_input",
]

#: box growth around an alpha cut-out, as a fraction of the box size on every side (CUB's 0.05 plus margin)
DEFAULT_PADDING = 0.1
#: the most padding: the framed square is then at most 21 times the box's side
MAX_PADDING = 10.0
#: the largest side of a framed crop with no image byte limit (2^31 pixels: beyond what any image holds, and within
#: the integers the crop is computed in)
MAX_CROP_SIDE = 2**31


class InputNotAFileError(UserError, OSError):
    """An input named on the command line exists but is neither a file nor a folder."""


def collect_inputs(
    inputs: str | os.PathLike | Sequence[str | os.PathLike], leave_out: str | os.PathLike | None = None
) -> list[Path]:
    """Image files named on the command line: files as given, folders searched recursively (sorted;
    :func:`~unicorn.data.folder.list_images`). One path on its own is one input. A file reached twice (named twice,
    or also through a link to it) is read once, under the name it was first reached by, or its own name where
    another was a link to it (a folder holding ``car.png`` and ``link.png -> car.png`` gives ``car.png``).

    A folder search leaves out ``leave_out`` (the command's output folder) and the output folders of
    ``unicorn-reconstruct`` and ``unicorn-eval`` (:func:`~unicorn.data.folder.is_output_folder`), so that outputs
    written inside an input folder are not read back as photos by a later run.

    Raises:
        FileNotFoundError: an input does not exist, a folder holds no images but outputs (the message says so), or
            nothing to read was found at all.
        InputNotAFileError: an input is a device, a pipe or a socket.
        TypeError: a path given as bytes.
    """
    if isinstance(inputs, (str, bytes, bytearray, os.PathLike)):  # not its characters, each an input ("/" among them)
        inputs = [inputs]
    inputs = list(inputs)
    if any(isinstance(item, (bytes, bytearray)) for item in inputs):
        raise TypeError("collect_inputs takes paths as str or os.PathLike, not bytes (decode them first)")
    files: list[Path] = []
    for item in inputs:
        path = Path(item).expanduser()
        if path.is_dir():
            outputs: dict[Path, bool] = {}  # folder -> whether it lies in an output (each folder looked at once)
            listed = list_images(path)
            found = [f for f in listed if not _in_output(f.parent, path, leave_out, outputs)]
            if not found:
                # the user sees images in the folder: say why none is read
                why = (
                    " other than outputs, which are not read (the output folder's, or an earlier run's)"
                    if listed
                    else ""
                )
                raise FileNotFoundError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in folder {path}{why}")
            files += found
        elif path.is_file():
            files.append(path)
        elif path.exists():
            raise InputNotAFileError(f"input {path} is not an image file or a folder (a device, a pipe or a socket)")
        else:
            raise FileNotFoundError(f"input not found: {path}")
    if not files:
        raise FileNotFoundError("no input images given")
    kept: dict[str, Path] = {}  # a file reached twice is read once: as first named, or by its own name over a link's
    for f in files:
        real = os.path.realpath(f)
        if real not in kept or (kept[real].is_symlink() and not f.is_symlink()):
            kept[real] = f
    return [f for f in files if kept[os.path.realpath(f)] is f]


def _in_output(folder: Path, searched: Path, leave_out: str | os.PathLike | None, known: dict[Path, bool]) -> bool:
    """Whether ``folder`` (``searched`` or below it) lies in ``leave_out``, or is a command's output folder
    (:func:`~unicorn.data.folder.is_output_folder`) or lies in one below ``searched``; ``known`` keeps the answers of
    the folders looked at."""
    if folder not in known:
        here = (
            leave_out is not None and Path(os.path.abspath(folder)).is_relative_to(os.path.abspath(leave_out))
        ) or is_output_folder(folder)
        known[folder] = here or (folder != searched and _in_output(folder.parent, searched, leave_out, known))
    return known[folder]


def alpha_bbox(path: str | os.PathLike, threshold: float = 0.5) -> np.ndarray | None:
    """Box ``(x1, y1, x2, y2)`` (0-based, inclusive) of the opaque pixels of an image with transparency, in the
    pixel grid of :func:`~unicorn.data.images.load_image` (EXIF orientation applied).

    Returns:
        the box, or None when the image has no alpha channel or is fully opaque.

    Raises:
        ImageLoadError: the image has no pixel more opaque than ``threshold``: nothing to reconstruct (framed whole,
            it would be a blank frame).
    """
    return _opaque_box(_alpha(path), path, threshold)


def _opaque_box(alpha: np.ndarray | None, path: str | os.PathLike, threshold: float = 0.5) -> np.ndarray | None:
    """:func:`alpha_bbox` of an image's opacity (None: no transparency)."""
    if alpha is None:
        return None
    opaque = alpha > threshold
    if not opaque.any():
        raise ImageLoadError(path, f"it has no opaque pixel (none above {threshold:.0%} alpha): nothing to reconstruct")
    if opaque.all():
        return None
    rows, cols = np.flatnonzero(opaque.any(axis=1)), np.flatnonzero(opaque.any(axis=0))
    return np.array([cols[0], rows[0], cols[-1], rows[-1]], dtype=np.float64)


def _alpha(path: str | os.PathLike) -> np.ndarray | None:
    """(H, W) opacity of an image with transparency in :func:`~unicorn.data.images.load_image`'s pixel grid, or
    None."""
    with open_image(path, path) as img:
        if not has_transparency(img):
            return None
        # oriented as load_image orients the image, so that a box is in its pixel grid
        return transparency_alpha(decoded(img, path))


class BoxError(UserError, ValueError):
    """An object box that is not finite, does not overlap its image, or frames a crop above the image limit."""


def check_box(bbox: Sequence[float], width: int, height: int, where: str) -> np.ndarray:
    """The box ``(x1, y1, x2, y2)`` (0-based, inclusive) as an array, checked against a ``width`` x ``height``
    image (``where`` names it in the message).

    Raises:
        BoxError: a box that is not four finite numbers with ``x2 > x1`` and ``y2 > y1``, or that does not overlap
            the image.
    """
    box = np.asarray(bbox, dtype=np.float64).reshape(-1)
    text = ",".join(f"{v:g}" for v in box)
    if box.shape != (4,) or not np.isfinite(box).all() or box[2] <= box[0] or box[3] <= box[1]:
        raise BoxError(f"bbox {text}: need four finite numbers x1,y1,x2,y2 with x2 > x1 and y2 > y1")
    if box[0] > width - 1 or box[1] > height - 1 or box[2] < 0 or box[3] < 0:
        raise BoxError(f"bbox {text} does not overlap {where} ({width} x {height} pixels)")
    return box


def check_padding(padding: float, name: str = "padding") -> float:
    """``padding`` if it is a finite fraction in [0, :data:`MAX_PADDING`]; ``name`` names it in the error.

    Raises:
        BoxError: anything else (NaN and infinity included).
    """
    number = isinstance(padding, int | float) and not isinstance(padding, bool)
    if not (number and math.isfinite(padding) and 0 <= padding <= MAX_PADDING):
        shown = f"{padding:g}" if number else repr(padding)  # a string or None has no number format
        raise BoxError(
            f"{name} {shown}: must be a finite number in [0, {MAX_PADDING:g}] (the margin added on every side of "
            "the object's box, as a fraction of its side)"
        )
    return float(padding)


def preprocess(
    image: np.ndarray, size: int, bbox: np.ndarray | Sequence[float] | None = None, padding: float = DEFAULT_PADDING
) -> np.ndarray:
    """Frame an image as the training data was: square crop around ``bbox`` or fit-and-pad, then resize.

    Raises:
        BoxError: the padded square crop would exceed the image byte limit (``UNICORN_MAX_IMAGE_BYTES``).

    Args:
        image: (H, W, 3) float array in [0, 1].
        size: the model's input side.
        bbox: ``(x1, y1, x2, y2)`` 0-based inclusive box of the object, or None for the whole image.
        padding: fraction of the box size added on every side before squaring it.

    Returns:
        (size, size, 3) float32 array.
    """
    return _framed(image, size, bbox, padding)[0]


#: a rectangle of an image, ``(x, y, width, height)`` in its pixels: x right, y down, pixel (i, j) spans
#: [j, j + 1) x [i, i + 1)
Rectangle = tuple[float, float, float, float]


def _framed(
    image: np.ndarray,
    size: int,
    bbox: np.ndarray | Sequence[float] | None,
    padding: float,
    fill: float | None = None,
) -> tuple[np.ndarray, Rectangle]:
    """:func:`preprocess`'s image and the rectangle of ``image`` it shows (beyond the image's edges where it pads).

    ``fill``: the value of the framed pixels beyond the image's edges (None: its border pixels repeated, as the
    training crops of photos are)."""
    if bbox is None:
        H, W = image.shape[:2]
        h, w, top, left = fit_layout(H, W, size)
        sx, sy = w / W, h / H  # the resized image's pixels per original pixel
        return fit_and_pad(image, size, fill).astype(np.float32), (-left / sx, -top / sy, size / sx, size / sy)
    box = pad_bbox(np.asarray(bbox, dtype=np.float64), check_padding(padding))
    side = float(max(box[2] - box[0], box[3] - box[1]) + 1)  # before the integers, which a huge box overflows
    shown = f"{side:.0f}" if side < 1e15 else f"{side:.3g}"
    limit = max_image_bytes()
    if limit is not None and side * side * RGB_BYTES_PER_PIXEL > limit:
        raise BoxError(
            f"the box with its padding frames a crop of {shown} x {shown} pixels, above the image limit of {limit} "
            "bytes (UNICORN_MAX_IMAGE_BYTES); give a smaller bbox or padding"
        )
    if side > MAX_CROP_SIDE:
        raise BoxError(
            f"the box with its padding frames a crop of {shown} x {shown} pixels, more than any image holds (at most "
            f"{MAX_CROP_SIDE} a side); give a smaller bbox or padding"
        )
    square = square_bbox(box)
    crop, _ = crop_box(image, square, fill=fill)
    side = float(square[2] - square[0] + 1)
    return resize_image(crop.astype(np.float32), (size, size)), (float(square[0]), float(square[1]), side, side)


class RawInput:
    """A user image read from disk, before framing.

    Attributes:
        path: the file.
        image: (H, W, 3) float32 array in [0, 1] (transparent pixels composited on white).
        bbox: the object box (from the alpha channel or given), or None.
        cutout: whether the image has transparent pixels (a cut-out): its frame is white beyond the image's edges
            (its background), rather than the image's border repeated (a photo's).
    """

    def __init__(self, path: Path, image: np.ndarray, bbox: np.ndarray | None, cutout: bool = False) -> None:
        self.path, self.image, self.bbox, self.cutout = path, image, bbox, cutout


class InputImage:
    """One preprocessed user image.

    Attributes:
        path: the file.
        name: a file-system safe name for its outputs (the stem, made unique by the caller).
        image: (3, S, S) float tensor in [0, 1], the model's input.
        cropped: whether an alpha cut-out (or a given box) set the framing.
        frame: the rectangle ``(x, y, width, height)`` of the file's image that ``image`` shows, in its pixels (x
            right, y down, pixel (i, j) spanning [j, j + 1) x [i, i + 1); beyond the image's edges where the framing
            pads it); None when unknown.
    """

    def __init__(
        self, path: Path, name: str, image: torch.Tensor, cropped: bool, frame: Rectangle | None = None
    ) -> None:
        self.path, self.name, self.image, self.cropped, self.frame = path, name, image, cropped, frame


def read_input(path: str | os.PathLike, bbox: Sequence[float] | None = None, use_alpha: bool = True) -> RawInput:
    """Read one image and find its object box (``bbox`` if given, else its alpha cut-out when ``use_alpha``).

    Raises:
        ImageLoadError: the file is not a readable image, or (``use_alpha`` without ``bbox``) a fully transparent one.
        BoxError: ``bbox`` is not finite or does not overlap the image.
    """
    path = Path(path)
    image, alpha = load_image_and_alpha(path)
    box = None if bbox is None else check_box(bbox, image.shape[1], image.shape[0], str(path))
    if box is None and use_alpha:
        box = _opaque_box(alpha, path)
    return RawInput(path, image, box, cutout=alpha is not None and bool((alpha < 1).any()))


def frame_input(raw: RawInput, size: int, name: str | None = None, padding: float = DEFAULT_PADDING) -> InputImage:
    """Frame a read image for a model of input side ``size`` (see the module docstring).

    Raises:
        ValueError: ``size`` is not a positive int.
    """
    if not is_whole(size) or size <= 0:
        raise ValueError(f"size must be a positive int (the model's input side in pixels), got {size!r}")
    framed, frame = _framed(raw.image, size, raw.bbox, padding, 1.0 if raw.cutout else None)
    return InputImage(raw.path, name or raw.path.stem, to_chw_tensor(framed), raw.bbox is not None, frame)


def load_input(
    path: str | os.PathLike,
    size: int,
    name: str | None = None,
    bbox: Sequence[float] | None = None,
    use_alpha: bool = True,
    padding: float = DEFAULT_PADDING,
) -> InputImage:
    """Read and frame one image: :func:`read_input` then :func:`frame_input`.

    Raises:
        ImageLoadError: the file is not a readable image.
        ValueError: ``size`` is not a positive int.
    """
    return frame_input(read_input(path, bbox, use_alpha), size, name, padding)
