"""CUB-200-2011 birds with the CMR annotations (boxes, masks, 15 keypoints).

Expected layout (``root`` = ``datasets/cub_200``)::

    images/<class_dir>/<file>.jpg                      # CUB_200_2011/images
    cachedir/cub/data/{train,val,test}_cub_cleaned.mat # CMR annotations, struct array 'images'
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from unicorn.data.annotated import BBoxCropDataset
from unicorn.data.common import OnError
from unicorn.data.images import DatasetError, require
from unicorn.data.matlab import load_struct_array

__all__ = ["CUB_KEYPOINTS", "CUB_FLIP_PERM", "CUB200"]

CUB_KEYPOINTS = (
    "Back",
    "Beak",
    "Belly",
    "Breast",
    "Crown",
    "FHead",
    "LEye",
    "LLeg",
    "LWing",
    "Nape",
    "REye",
    "RLeg",
    "RWing",
    "Tail",
    "Throat",
)
#: 0-based permutation swapping left and right keypoints under a horizontal flip (CMR's order)
CUB_FLIP_PERM = np.array([1, 2, 3, 4, 5, 6, 11, 12, 13, 10, 7, 8, 9, 14, 15]) - 1

_IMAGES_HINT = (
    "Download CUB_200_2011.tgz (https://www.vision.caltech.edu/datasets/cub_200_2011/), extract it and "
    "rename the CUB_200_2011 folder to the dataset root, so that it holds images/<class>/<file>.jpg."
)
_ANNO_HINT = (
    "The annotations come from CMR's cachedir (github.com/akanazawa/cmr, doc/train.md, 'cachedir' archive) "
    "or UCMR's cachedir.tar.gz: put cub/data/{train,val,test}_cub_cleaned.mat under <root>/cachedir/."
)


class CUB200(BBoxCropDataset):
    """CUB-200-2011 crops with masks and keypoints.

    Args:
        root: dataset root (holds ``images/`` and ``cachedir/``).
        split: ``"train"``, ``"val"`` or ``"test"`` (CMR's cleaned splits).
        img_size: side of the returned images (64 in UNICORN).
        augment: box jitter and random flips; defaults to True for ``"train"`` only.
        jitter: fraction of the box size by which each training box's corners move at random when augmenting
            (None: the reference's 0.05; 0: crops centred on the box), in [0, 0.5).
        eval_size: resolution of masks and keypoints if different from ``img_size`` (256 for PCK).
        on_error: ``"raise"`` or ``"skip"`` unreadable images.

    Items: ``image`` (3, S, S), ``mask`` (1, M, M), ``keypoints`` (15, 3), dummy ``R``/``T`` with
    ``has_pose`` False, ``flipped``; S = ``img_size``, M = ``eval_size or img_size``.
    """

    padding = 0.05
    jitter = 0.05

    def __init__(
        self,
        root: str | Path,
        split: Literal["train", "val", "test"] = "train",
        img_size: int = 64,
        augment: bool | None = None,
        jitter: float | None = None,
        eval_size: int | None = None,
        on_error: OnError = "raise",
    ) -> None:
        if split not in ("train", "val", "test"):
            raise DatasetError(f"split must be 'train', 'val' or 'test', got {split!r}")
        root = require(root, "CUB-200-2011 root", _IMAGES_HINT)
        image_dir = require(root / "images", "CUB-200-2011 images folder", _IMAGES_HINT)
        anno = require(
            root / "cachedir" / "cub" / "data" / f"{split}_cub_cleaned.mat", "CUB annotation file", _ANNO_HINT
        )
        self.root, self.split = root, split
        super().__init__(
            load_struct_array(anno, "images"),
            image_dir,
            img_size=img_size,
            padding=self.padding,
            jitter=self.jitter if jitter is None else jitter,
            augment=(split == "train") if augment is None else augment,
            eval_size=eval_size,
            flip_perm=CUB_FLIP_PERM,
            on_error=on_error,
            source=anno,
        )
