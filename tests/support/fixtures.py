"""Fixtures shared by several test packages: datasets in the real on-disk formats, the synthetic set, a cache."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch

from tests.support.datasets import write_annotated_split
from tests.support.prepared import generated
from unicorn.data.cub import CUB_KEYPOINTS


@pytest.fixture
def cub_root(tmp_path: Path) -> Path:
    """CUB-200-2011 layout: images/<class>/<file>.jpg + cachedir/cub/data/<split>_cub_cleaned.mat."""
    root = tmp_path / "cub_200"
    dirs = ["001.Black_footed_Albatross", "002.Laysan_Albatross"]
    for seed, (split, n) in enumerate([("train", 4), ("val", 7), ("test", 3)]):
        write_annotated_split(
            root,
            "images",
            root / "cachedir/cub/data" / f"{split}_cub_cleaned.mat",
            dirs,
            n,
            len(CUB_KEYPOINTS),
            seed,
        )
    return root


@pytest.fixture
def p3d_root(tmp_path: Path) -> Path:
    """Pascal3D+ layout with UCMR annotations, car_kps.mat and the 10 CAD point clouds."""
    root = tmp_path / "pascal_3d"
    dirs = ["car_pascal", "car_imagenet"]
    for seed, (split, n) in enumerate([("train", 3), ("test", 2)]):
        write_annotated_split(root, "Images", root / "ucmr_anno/data" / f"car_{split}.mat", dirs, n, 12, seed + 10)
    perm = np.array([2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11])  # 1-based, like the real file
    names = np.array([f"kp{i}" for i in range(12)], dtype=object)
    scipy.io.savemat(root / "ucmr_anno/data/car_kps.mat", {"kp_names": names, "kp_perm_inds": perm})
    pc_dir = root / "unicorn_anno/car"
    pc_dir.mkdir(parents=True)
    for k in range(1, 11):
        pts = torch.rand(200, 3) - 0.5
        torch.save(
            {"points": pts, "normals": torch.nn.functional.normalize(pts, dim=1)},
            pc_dir / f"{k:02d}_pointcloud.pt",
        )
    return root


@pytest.fixture(scope="session")
def synth_nmr(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Synthetic benchmark, NMR mode: 2 categories x 3 models x 6 views (also the ShapeNet-NMR fixture)."""
    return generated("nmr", tmp_path_factory.mktemp("synth") / "nmr")


@pytest.fixture(scope="session")
def synth_wild(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Synthetic benchmark, wild mode (off-centre cameras, roll, random backgrounds)."""
    return generated("wild", tmp_path_factory.mktemp("synth") / "wild")


@pytest.fixture(scope="session")
def synthetic_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache holding the 5-model synthetic set at 32 px; ``UNICORN_CACHE`` points at it (also for subprocesses)."""
    cache = generated("cache", tmp_path_factory.mktemp("unicorn_cache"))
    old = os.environ.get("UNICORN_CACHE")
    os.environ["UNICORN_CACHE"] = str(cache)
    yield cache
    if old is None:
        os.environ.pop("UNICORN_CACHE", None)
    else:
        os.environ["UNICORN_CACHE"] = old
