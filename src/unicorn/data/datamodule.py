"""One LightningDataModule for every dataset: builds the splits, the validation subset and the loaders.

Dataset names: ``shapenet_nmr``, ``synthetic`` (generated on first use, then read as ShapeNet-NMR),
``cub_200``, ``p3d_car``, ``compcars``, ``lsun``, ``folder``. Splits follow the reference: ShapeNet uses the
SoftRas lists (training on every view, evaluation on one fixed random view per model); CUB its CMR splits;
Pascal3D+ car has train / test and validates on training images; CompCars, LSUN and folders have no split
(every image is used for training and testing). Validation runs on a small subset, as in the reference, capped
at the dataset size.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Subset

from unicorn.data.common import OnError
from unicorn.data.cub import CUB200
from unicorn.data.folder import CompCars, ImageFolder
from unicorn.data.images import DatasetError, set_max_image_pixels
from unicorn.data.lsun import LSUN
from unicorn.data.p3d import Pascal3DCar
from unicorn.data.shapenet import ShapeNetNMR

__all__ = ["DATASET_NAMES", "VAL_SIZES", "UnicornDataModule", "build_dataset", "val_indices"]


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


class UnicornDataModule(L.LightningDataModule):
    """Train / val / test loaders for one dataset.

    Args:
        name: one of :data:`DATASET_NAMES`.
        root: dataset root; for ``synthetic`` the parent folder of generated datasets (default: the cache,
            ``$UNICORN_CACHE/synthetic`` or ``~/.cache/unicorn/synthetic``).
        categories: ShapeNet categories (names or synsets); for ``synthetic`` the generated categories.
        img_size: image side.
        batch_size: training batch size (evaluation uses the same).
        num_workers: DataLoader worker processes.
        seed: seeds the training shuffle and the evaluation view choice.
        val_size: validation subset size, default :data:`VAL_SIZES` (capped at the split size).
        on_error: ``"raise"`` or ``"skip"`` unreadable images.
        pin_memory: pin batches (for GPU training).
        synthetic: for ``synthetic``: ``mode`` (``"nmr"``/``"wild"``), ``n_models``, ``seed`` and other
            :func:`~unicorn.data.synthetic.writer.generate_synthetic_dataset` options.
        options: extra dataset-constructor arguments (e.g. ``{"tag": "horse"}`` for LSUN).
        max_image_pixels: refuse images with more pixels (a bad image, skipped with ``on_error="skip"``); None:
            the current limit (:func:`unicorn.data.images.max_image_pixels`), 0: no limit. Set for the whole
            process and its workers.
    """

    def __init__(
        self,
        name: str,
        root: str | None = None,
        categories: str | list[str] | None = None,
        img_size: int = 64,
        batch_size: int = 32,
        num_workers: int = 4,
        seed: int = 0,
        val_size: int | None = None,
        on_error: OnError = "raise",
        pin_memory: bool = False,
        synthetic: dict[str, Any] | None = None,
        options: dict[str, Any] | None = None,
        max_image_pixels: int | None = None,
    ) -> None:
        super().__init__()
        if max_image_pixels is not None:
            set_max_image_pixels(max_image_pixels)
        if name not in DATASET_NAMES:
            raise DatasetError(f"unknown dataset {name!r}; choose from {list(DATASET_NAMES)}")
        if name != "synthetic" and root is None:
            raise DatasetError(f"dataset {name!r} needs a root folder (dataset.root)")
        self.name, self.root, self.img_size = name, root, int(img_size)
        # Hydra passes lists as ListConfig: normalise to plain str / list[str]
        if categories is None or isinstance(categories, str):
            self.categories = categories
        else:
            self.categories = [str(c) for c in categories]
        self.batch_size, self.num_workers, self.seed = int(batch_size), int(num_workers), int(seed)
        self.val_size, self.on_error, self.pin_memory = val_size, on_error, pin_memory
        self.synthetic = {"mode": "nmr", "n_models": 200, "seed": 0, **dict(synthetic or {})}
        self.options = dict(options or {})
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None
        self.test_set: Dataset | None = None

    def _synthetic_args(self) -> dict[str, Any]:
        cats = self.categories if self.categories is not None else "chair"
        return {"root": self.root, "category": cats, **self.synthetic}

    def dataset_root(self) -> Path:
        """Folder the datasets are read from (for ``synthetic``: the generated dataset)."""
        if self.name == "synthetic":
            # imported here: the generator pulls in open3d, which real-data training never needs
            from unicorn.data.synthetic.writer import synthetic_dataset_path

            args = self._synthetic_args()
            return synthetic_dataset_path(args["category"], args["mode"], args["n_models"], args["seed"], self.root)
        return Path(str(self.root))

    def prepare_data(self) -> None:
        """Generate the synthetic dataset if it is absent (runs on one process only)."""
        if self.name == "synthetic":
            from unicorn.data.synthetic.writer import ensure_synthetic_dataset

            ensure_synthetic_dataset(**self._synthetic_args())

    def build(self, split: Split) -> Dataset:
        """The full dataset of ``split`` (see :func:`build_dataset`)."""
        return build_dataset(
            self.name,
            split,
            self.dataset_root(),
            img_size=self.img_size,
            categories=self.categories,
            seed=self.seed,
            on_error=self.on_error,
            **self.options,
        )

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit") and self.train_set is None:
            self.train_set = self.build("train")
        if stage in (None, "fit", "validate") and self.val_set is None:
            full = self.build("val")
            self.val_set = Subset(full, val_indices(self.name, len(full), self.val_size))
        if stage in (None, "test", "predict") and self.test_set is None:
            self.test_set = self.build("test")

    def _loader(self, dataset: Dataset | None, train: bool) -> DataLoader:
        if dataset is None:
            raise RuntimeError("call setup() before asking for a dataloader")
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            shuffle=train,
            drop_last=train and len(dataset) >= self.batch_size,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.num_workers > 0,
            generator=torch.Generator().manual_seed(self.seed) if train else None,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, train=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, train=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.test_set, train=False)
