"""Unannotated image collections: any folder of images, and CompCars.

Images are read upright by their EXIF orientation (a phone photo stored sideways reaches the network as it is
shown), resized so that their longer side is ``img_size`` and padded to a square by replicating their border (the
reference's ``resize_mode='pad'``); training items are flipped horizontally at random.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from unicorn.data.common import OnError, UnicornDataset, dummy_pose, item_rng
from unicorn.data.framing import fit_and_pad
from unicorn.data.images import DatasetError, DatasetNotFoundError, load_image, require, to_chw_tensor
from unicorn.errors import UnicornWarning

__all__ = [
    "EVALUATION_RECORDS",
    "IMAGE_EXTENSIONS",
    "RECONSTRUCTIONS_RECORD",
    "CompCars",
    "ImageFolder",
    "UnreadableFolderWarning",
    "is_output_folder",
    "list_images",
    "unannotated_item",
]

#: HEIF needs pillow-heif (the ``heif`` extra) and AVIF Pillow 11.3: without them their files fail to read, one line
#: each saying what to install, rather than going unnoticed
IMAGE_EXTENSIONS = (
    ".jpg",
    ".jpeg",
    ".png",
    ".ppm",
    ".bmp",
    ".tif",
    ".tiff",
    ".webp",
    ".gif",
    ".heic",
    ".heif",
    ".avif",
)

_COMPCARS_HINT = (
    "CompCars comes as GIRAFFE's comprehensive_cars.zip (github.com/autonomousvision/giraffe, "
    "scripts/download_dataset.sh): extract it and rename comprehensive_cars to the dataset root, so that it "
    "holds images/*.jpg."
)


#: the file ``unicorn-reconstruct`` writes at the top of its output folder: a folder holding it is its output
RECONSTRUCTIONS_RECORD = "reconstructions.json"
#: the files ``unicorn-eval`` writes at the top of its output folder: a folder holding both is its output
EVALUATION_RECORDS = ("metrics.json", "per_image.csv")


def is_output_folder(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` is the output of ``unicorn-reconstruct`` or ``unicorn-eval`` (:data:`RECONSTRUCTIONS_RECORD`,
    :data:`EVALUATION_RECORDS`): its pictures are not photos to read."""
    # os.path.isfile: a folder that cannot be searched (no permission) holds no record, rather than raising
    return os.path.isfile(Path(folder, RECONSTRUCTIONS_RECORD)) or all(
        os.path.isfile(Path(folder, n)) for n in EVALUATION_RECORDS
    )


def list_images(root: Path, extensions: tuple[str, ...] = IMAGE_EXTENSIONS) -> list[Path]:
    """All files under ``root`` (recursively) whose suffix, lower-cased, is in ``extensions``; sorted.

    Links to folders are followed, each folder read once (so a link back up the tree ends there); a link named like an
    image that leads nowhere (dangling, or a loop of links) is listed, so that reading it fails as a corrupt image
    does (``on_error="skip"`` skips it with a warning) rather than the image going missing unnoticed. Paths are
    given through the links, not resolved. A folder that cannot be read (no permission) is named in a warning: its
    images are left out. Hidden files and folders (names starting with ``.``: a Mac's ``._IMG_1.jpg`` resource
    files, ``.thumbnails/``, temporary folders) are left out too, and so are the output folders of unicorn's commands
    below ``root`` (:func:`is_output_folder`: a report's pictures written inside an image folder are not read back as
    photos).
    """
    found, seen = [], set()
    for folder, subfolders, files in os.walk(root, followlinks=True, onerror=_unreadable_folder):
        real = os.path.realpath(folder)
        if real in seen:
            subfolders.clear()  # reached before by another route
            continue
        seen.add(real)
        # hidden folders left out; sorted, so that which route reaches a folder first does not depend on the disk
        subfolders[:] = sorted(
            name for name in subfolders if not name.startswith(".") and not is_output_folder(Path(folder, name))
        )
        for name in files:
            if name.startswith("."):
                continue
            path = Path(folder, name)
            # a regular file (through any links), or a broken link; not a pipe or a device
            if path.suffix.lower() in extensions and (path.is_file() or not path.exists()):
                found.append(path)
    return sorted(found)


class UnreadableFolderWarning(UnicornWarning, RuntimeWarning):
    """A folder under an image folder could not be read (no permission): its images are left out."""


def _unreadable_folder(err: OSError) -> None:
    warnings.warn(
        f"cannot read the folder {err.filename}: {err.strerror or err}; the images in it are left out",
        UnreadableFolderWarning,
        stacklevel=3,
    )


def unannotated_item(image: np.ndarray, img_size: int, flip: bool) -> dict[str, Any]:
    """Item dict for an image without annotations: fit-and-pad, optional flip, dummy pose, all-ones mask."""
    image = fit_and_pad(image, img_size)
    if flip:
        image = image[:, ::-1]
    R, T = dummy_pose()
    return {
        "image": to_chw_tensor(image),
        "mask": torch.ones(1, img_size, img_size),
        "R": R,
        "T": T,
        "has_pose": torch.tensor(False),
        "has_mask": torch.tensor(False),
    }


def _suffixes(extensions: str | Sequence[str]) -> tuple[str, ...]:
    """Lower-case file suffixes with their dot: ``png``, ``.PNG`` and ``.png`` are one (a config's list of bare
    extensions would otherwise match no file)."""
    given = [extensions] if isinstance(extensions, str) else list(extensions)
    return tuple(("" if str(e).startswith(".") else ".") + str(e).lower() for e in given)


class ImageFolder(UnicornDataset):
    """Every image under a folder (recursively), for training on one's own photos.

    Args:
        root: folder of images (any depth).
        img_size: side of the returned square images.
        augment: random horizontal flips (training).
        extensions: accepted file suffixes, with or without their dot (case-insensitive): ``(".jpg", "png")``, or
            one as a string.
        on_error: ``"raise"`` or ``"skip"`` unreadable images.

    Items: ``image`` (3, S, S), ``mask`` (1, S, S) of ones (``has_mask`` False), dummy pose.
    """

    hint = "Point the dataset root at a folder that contains images (searched recursively)."

    def __init__(
        self,
        root: str | Path,
        img_size: int = 64,
        augment: bool = False,
        extensions: str | Sequence[str] = IMAGE_EXTENSIONS,
        on_error: OnError = "raise",
    ) -> None:
        super().__init__(on_error)
        self.root = require(root, "image folder", self.hint)
        folder = require(self.image_root(), "image folder", self.hint)
        if not folder.is_dir():
            raise DatasetError(f"{folder} is a file, not a folder of images. {self.hint}")
        suffixes = _suffixes(extensions)
        self.files = list_images(folder, suffixes)
        if not self.files:
            raise DatasetNotFoundError(self.image_root() / "*", f"images with suffix {list(suffixes)}", self.hint)
        self.img_size = int(img_size)
        self.augment = bool(augment)

    def image_root(self) -> Path:
        return self.root

    def __len__(self) -> int:
        return len(self.files)

    def load(self, index: int) -> dict[str, Any]:
        image = load_image(self.files[index])
        flip = self.augment and item_rng().random() < 0.5
        return unannotated_item(image, self.img_size, flip)


class CompCars(ImageFolder):
    """CompCars web car images (GIRAFFE's copy), ``<root>/images/**/*.jpg``; no annotations, no split.

    Args:
        root: dataset root (holds ``images/``).
        img_size: side of the returned square images.
        augment: random horizontal flips (training).
        on_error: ``"raise"`` or ``"skip"`` unreadable images.
    """

    hint = _COMPCARS_HINT

    def __init__(
        self, root: str | Path, img_size: int = 64, augment: bool = False, on_error: OnError = "raise"
    ) -> None:
        require(Path(root) / "images", "CompCars images folder", _COMPCARS_HINT)
        super().__init__(root, img_size=img_size, augment=augment, extensions=(".jpg", ".jpeg"), on_error=on_error)

    def image_root(self) -> Path:
        return self.root / "images"
