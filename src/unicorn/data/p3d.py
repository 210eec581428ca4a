"""Pascal3D+ Car with the UCMR annotations and UNICORN's CAD point clouds.

Expected layout (``root`` = ``datasets/pascal_3d``)::

    Images/car_pascal/<voc_id>.jpg, Images/car_imagenet/<id>.JPEG   # PASCAL3D+_release1.1/Images
    ucmr_anno/data/car_train.mat, car_test.mat                      # UCMR 'images' struct arrays
                                                                    #   (car_test.mat = UCMR's car_val.mat)
    ucmr_anno/data/car_kps.mat                                      # optional: kp_names, kp_perm_inds
    unicorn_anno/car/01_pointcloud.pt ... 10_pointcloud.pt          # {'points', 'normals'} per CAD model
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from unicorn.data.annotated import BBoxCropDataset
from unicorn.data.common import OnError
from unicorn.data.images import DatasetError, DatasetNotFoundError, require
from unicorn.data.matlab import load_struct_array, read_mat
from unicorn.torch_files import TorchFileError, read_plain

__all__ = ["Pascal3DCar", "load_cad_pointclouds"]

N_CAD_MODELS = 10

_IMAGES_HINT = (
    "Download PASCAL3D+_release1.1 (https://cvgl.stanford.edu/projects/pascal3d.html) and use its folder as "
    "the dataset root, so that it holds Images/car_pascal and Images/car_imagenet."
)
_ANNO_HINT = (
    "The annotations come from UCMR (github.com/shubham-goel/ucmr, docs/training.md, "
    "cachedir-others.tar.gz): put its cachedir/p3d files under <root>/ucmr_anno/ "
    "(data/car_train.mat; rename car_val.mat to car_test.mat)."
)
_PC_HINT = (
    "The CAD point clouds come from UNICORN's unicorn_anno.zip (github.com/monniert/unicorn, "
    "scripts/download_data.sh): extract it to <root>/unicorn_anno/ "
    "(car/01_pointcloud.pt ... 10_pointcloud.pt)."
)


def load_cad_pointclouds(root: str | Path) -> list[dict[str, torch.Tensor]]:
    """The 10 Pascal3D+ car CAD point clouds, index k-1 for ``cad_index`` k.

    Returns:
        A list of dicts with ``points`` and ``normals`` (P, 3) float32.
    """
    folder = require(Path(root) / "unicorn_anno" / "car", "Pascal3D+ CAD point-cloud folder", _PC_HINT)
    clouds = []
    for k in range(1, N_CAD_MODELS + 1):
        path = folder / f"{k:02d}_pointcloud.pt"
        if not path.exists():
            raise DatasetNotFoundError(path, "Pascal3D+ CAD point cloud", _PC_HINT)
        clouds.append(_read_pointcloud(path))
    return clouds


def _read_pointcloud(path: Path) -> dict[str, torch.Tensor]:
    """One CAD point cloud file: ``points`` and ``normals`` (P, 3) float32, read without unpickling code.

    Raises:
        DatasetError: the file is not such a point cloud (truncated, another format, other keys or shapes).
    """
    try:
        data = read_plain(path)
    except TorchFileError as err:
        raise DatasetError(f"cannot read the CAD point cloud {path}: {err}") from None
    keys = ("points", "normals")
    if not isinstance(data, dict) or any(k not in data for k in keys):
        found = sorted(map(str, data)) if isinstance(data, dict) else type(data).__name__
        raise DatasetError(f"the CAD point cloud {path} must hold 'points' and 'normals', got {found}")
    cloud = {k: torch.as_tensor(data[k], dtype=torch.float32) for k in keys}
    if any(t.dim() != 2 or t.shape[1] != 3 or t.shape[0] == 0 for t in cloud.values()):
        shapes = {k: tuple(t.shape) for k, t in cloud.items()}
        raise DatasetError(f"the CAD point cloud {path} must hold (P, 3) points and normals, got shapes {shapes}")
    if len(cloud["points"]) != len(cloud["normals"]) or not all(t.isfinite().all() for t in cloud.values()):
        counts = {k: len(t) for k, t in cloud.items()}
        raise DatasetError(f"the CAD point cloud {path}: points and normals must be as many and finite, got {counts}")
    return cloud


class Pascal3DCar(BBoxCropDataset):
    """Pascal3D+ car crops with masks, keypoints and (test split) the CAD point cloud of each car.

    Args:
        root: dataset root (holds ``Images/``, ``ucmr_anno/``, ``unicorn_anno/``).
        split: ``"train"`` or ``"test"`` (the reference's validation set is the first train images).
        img_size: side of the returned images (64 in UNICORN).
        augment: box jitter and random flips; defaults to True for ``"train"`` only.
        jitter: fraction of the box size by which each training box's corners move at random when augmenting
            (None: the reference's 0.1; 0: crops centred on the box), in [0, 0.5).
        eval_size: resolution of masks and keypoints if different from ``img_size``.
        with_points: add the ground-truth CAD point cloud (``points``, ``normals`` (P, 3)); defaults to True
            for ``"test"``.
        on_error: ``"raise"`` or ``"skip"`` unreadable images.

    Items: ``image`` (3, S, S), ``mask`` (1, M, M), ``keypoints`` (12, 3) when ``car_kps.mat`` exists, dummy
    ``R``/``T`` with ``has_pose`` False, ``cad_index`` (1-based), optionally ``points``/``normals``.
    """

    padding = 0.1
    jitter = 0.1

    def __init__(
        self,
        root: str | Path,
        split: Literal["train", "test"] = "train",
        img_size: int = 64,
        augment: bool | None = None,
        jitter: float | None = None,
        eval_size: int | None = None,
        with_points: bool | None = None,
        on_error: OnError = "raise",
    ) -> None:
        if split not in ("train", "test"):
            raise DatasetError(f"split must be 'train' or 'test', got {split!r}")
        root = require(root, "Pascal3D+ root", _IMAGES_HINT)
        image_dir = require(root / "Images", "Pascal3D+ images folder", _IMAGES_HINT)
        data_dir = root / "ucmr_anno" / "data"
        anno = require(data_dir / f"car_{split}.mat", "Pascal3D+ car annotation file", _ANNO_HINT)
        flip_perm = None
        kps_file = data_dir / "car_kps.mat"
        if kps_file.exists():
            kps = read_mat(kps_file, squeeze_me=True)
            if "kp_perm_inds" not in kps:
                names = sorted(k for k in kps if not k.startswith("__"))
                raise DatasetError(f"{kps_file} has no variable 'kp_perm_inds' (it has {names})")
            try:
                perm = np.atleast_1d(kps["kp_perm_inds"]).astype(np.float64)
            except (TypeError, ValueError):
                perm = None
            if perm is None or not (np.isfinite(perm).all() and (perm == np.round(perm)).all()):
                raise DatasetError(f"{kps_file}: kp_perm_inds must be whole numbers")
            flip_perm = perm.astype(np.int64) - 1  # MATLAB indices are 1-based
        self.root, self.split = root, split
        self.with_points = (split == "test") if with_points is None else with_points
        self.cad_pointclouds = load_cad_pointclouds(root) if self.with_points else None
        super().__init__(
            load_struct_array(anno, "images"),
            image_dir,
            img_size=img_size,
            padding=self.padding,
            jitter=self.jitter if jitter is None else jitter,
            augment=(split == "train") if augment is None else augment,
            eval_size=eval_size,
            flip_perm=flip_perm,
            on_error=on_error,
            source=anno,
        )

    def record_problem(self, record: Any) -> str | None:
        """The base class's checks, and a ``cad_index`` among the 10 CAD models (1-based)."""
        problem = super().record_problem(record)
        if problem is not None:
            return problem
        cad = record.get("cad_index")
        if not (isinstance(cad, (int, np.integer, float, np.floating)) and float(cad).is_integer()):
            return f"cad_index must be a whole number in [1, {N_CAD_MODELS}], got {cad!r}"
        if not 1 <= int(cad) <= N_CAD_MODELS:
            return f"cad_index must be in [1, {N_CAD_MODELS}] (the CAD models, 1-based), got {int(cad)}"
        return None

    def load(self, index: int) -> dict[str, Any]:
        item = super().load(index)
        cad_index = int(self.records[index]["cad_index"])
        item["cad_index"] = torch.tensor(cad_index, dtype=torch.int64)
        if self.cad_pointclouds is not None:
            item.update(self.cad_pointclouds[cad_index - 1])
        return item
