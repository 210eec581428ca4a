"""The dataset registry: every dataset by name, its splits, the validation subset, the synthetic set's folder.

Dataset names: ``shapenet_nmr``, ``synthetic`` (generated on first use, then read as ShapeNet-NMR),
``cub_200``, ``p3d_car``, ``compcars``, ``lsun``, ``folder``. Splits follow the reference: ShapeNet uses the
SoftRas lists (training on every view, evaluation on one fixed random view per model); CUB its CMR splits;
Pascal3D+ car has train / test and validates on training images; CompCars, LSUN and folders have no split
(every image is used for training and testing). Validation runs on a small subset, as in the reference, capped
at the dataset size. The Lightning DataModule built on these is :class:`unicorn.lit.UnicornDataModule`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
from torch.utils.data import Dataset

from unicorn.data.common import OnError
from unicorn.data.cub import CUB200
from unicorn.data.folder import CompCars, ImageFolder
from unicorn.data.images import DatasetError
from unicorn.data.lsun import LSUN
from unicorn.data.p3d import Pascal3DCar
from unicorn.data.shapenet import ShapeNetNMR

__all__ = [
    "DATASET_NAMES",
    "SYNTHETIC_DEFAULTS",
    "VAL_SIZES",
    "Split",
    "build_dataset",
    "dataset_root",
    "prepare_dataset",
    "synthetic_options",
    "val_indices",
]


Split = Literal["train", "val", "test"]

#: the reference's validation subset sizes
VAL_SIZES = {
    "shapenet_nmr": 32,
    "synthetic": 32,
    "cub_200": 5,
    "p3d_car": 5,
    "compcars": 5,
    "lsun": 5,
    "folder": 5,
}
DATASET_NAMES = tuple(VAL_SIZES)
#: the reference shuffles CUB's evaluation sets with this seed
_EVAL_SHUFFLE_SEED = 123
#: the reference's LSUN validation images start at this offset
_LSUN_VAL_OFFSET = 17
#: settings of a ``synthetic`` dataset left out of its config (the category when ``categories`` is None)
SYNTHETIC_DEFAULTS: dict[str, Any] = {"category": "chair", "mode": "nmr", "n_models": 200, "seed": 0}


def build_dataset(
    name: str,
    split: Split,
    root: str | os.PathLike,
    img_size: int = 64,
    categories: str | list[str] | None = None,
    seed: int = 0,
    on_error: OnError = "raise",
    **options: Any,
) -> Dataset:
    """The full dataset of one split (before the validation subset is taken).

    Args:
        name: one of :data:`DATASET_NAMES`.
        split: ``"train"``, ``"val"`` or ``"test"``; training splits are augmented where the reference does.
        root: dataset root (for ``synthetic``: the generated dataset folder).
        img_size: image side (ShapeNet-NMR images keep their stored size).
        categories: ShapeNet / synthetic categories.
        seed: seed of the fixed evaluation view choice (ShapeNet).
        on_error: ``"raise"`` or ``"skip"`` unreadable images.
        **options: extra constructor arguments of the dataset class (e.g. ``tag`` for LSUN, ``eval_size``).
    """
    if split not in ("train", "val", "test"):
        raise DatasetError(f"split must be 'train', 'val' or 'test', got {split!r}")
    train = split == "train"
    if name in ("shapenet_nmr", "synthetic"):
        # every view for training, one fixed random view per model for evaluation, unless told
        views = options.pop("views", "all" if train else "random")
        return ShapeNetNMR(root, categories, split, views=views, seed=seed, on_error=on_error, **options)
    if name == "cub_200":
        return CUB200(root, split, img_size=img_size, on_error=on_error, **options)
    if name == "p3d_car":
        # the reference validates on (unaugmented) training images
        p3d_split = "test" if split == "test" else "train"
        return Pascal3DCar(root, p3d_split, img_size=img_size, augment=train, on_error=on_error, **options)
    if name == "compcars":
        return CompCars(root, img_size=img_size, augment=train, on_error=on_error, **options)
    if name == "lsun":
        return LSUN(root, img_size=img_size, augment=train, on_error=on_error, **options)
    if name == "folder":
        return ImageFolder(root, img_size=img_size, augment=train, on_error=on_error, **options)
    raise DatasetError(f"unknown dataset {name!r}; choose from {list(DATASET_NAMES)}")


def val_indices(name: str, n: int, size: int | None = None) -> list[int]:
    """Indices of the validation subset of a split of ``n`` items, as the reference picks them.

    ShapeNet: the first models; CUB: the first after a seed-123 shuffle; LSUN: 5 images from offset 17;
    others: the first images. ``size`` defaults to :data:`VAL_SIZES` and is capped at ``n``.
    """
    size = min(VAL_SIZES.get(name, 5) if size is None else size, n)
    if name == "cub_200":
        return np.random.default_rng(_EVAL_SHUFFLE_SEED).permutation(n)[:size].tolist()
    if name == "lsun" and n >= _LSUN_VAL_OFFSET + size:
        return list(range(_LSUN_VAL_OFFSET, _LSUN_VAL_OFFSET + size))
    return list(range(size))


def synthetic_options(
    root: str | os.PathLike | None,
    categories: str | list[str] | None = None,
    synthetic: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The arguments of :func:`~unicorn.data.synthetic.writer.ensure_synthetic_dataset` for a ``synthetic`` dataset.

    Args:
        root: parent folder of generated datasets (None: the cache, ``$UNICORN_CACHE/synthetic``).
        categories: the generated categories (None: :data:`SYNTHETIC_DEFAULTS`).
        synthetic: ``mode``, ``n_models``, ``seed`` and other generator options over :data:`SYNTHETIC_DEFAULTS`.
    """
    category = SYNTHETIC_DEFAULTS["category"] if categories is None else categories
    return {**SYNTHETIC_DEFAULTS, "root": root, "category": category, **dict(synthetic or {})}


def dataset_root(
    name: str,
    root: str | os.PathLike | None,
    categories: str | list[str] | None = None,
    synthetic: dict[str, Any] | None = None,
) -> Path:
    """Folder a dataset is read from: ``root``, or for ``synthetic`` the generated dataset's folder under it."""
    if name == "synthetic":
        # imported here: the generator pulls in open3d, which real-data training never needs
        from unicorn.data.synthetic.writer import synthetic_dataset_path

        args = synthetic_options(root, categories, synthetic)
        return synthetic_dataset_path(args["category"], args["mode"], args["n_models"], args["seed"], args["root"])
    return Path(str(root))


def prepare_dataset(
    name: str,
    root: str | os.PathLike | None,
    categories: str | list[str] | None = None,
    synthetic: dict[str, Any] | None = None,
) -> Path:
    """Generate the ``synthetic`` dataset if it is absent (other datasets are read as they are); returns
    :func:`dataset_root`."""
    if name == "synthetic":
        from unicorn.data.synthetic.writer import ensure_synthetic_dataset

        return ensure_synthetic_dataset(**synthetic_options(root, categories, synthetic))
    return dataset_root(name, root)
