"""Datasets: real loaders in their on-disk formats, the synthetic benchmark, and the registry that builds them.

No Lightning here: the LightningDataModule is :class:`unicorn.lit.UnicornDataModule`. The synthetic benchmark
generator lives in :mod:`unicorn.data.synthetic` (generating a set needs open3d; reading one does not).
"""

from unicorn.data.common import PRIOR_TRANSLATION, UnicornDataset
from unicorn.data.cub import CUB200
from unicorn.data.folder import CompCars, ImageFolder
from unicorn.data.images import DatasetError, DatasetNotFoundError, ImageLoadError
from unicorn.data.lsun import LSUN
from unicorn.data.p3d import Pascal3DCar
from unicorn.data.registry import DATASET_NAMES, build_dataset, dataset_root, prepare_dataset
from unicorn.data.shapenet import ShapeNetNMR

__all__ = [
    "CUB200",
    "DATASET_NAMES",
    "LSUN",
    "PRIOR_TRANSLATION",
    "CompCars",
    "DatasetError",
    "DatasetNotFoundError",
    "ImageFolder",
    "ImageLoadError",
    "Pascal3DCar",
    "ShapeNetNMR",
    "UnicornDataset",
    "build_dataset",
    "dataset_root",
    "prepare_dataset",
]
