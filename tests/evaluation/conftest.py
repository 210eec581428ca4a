"""Fixtures of the evaluation tests: tiny models and checkpoints, the synthetic set, CUB / Pascal3D+ layouts."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.data.conftest import cub_root, p3d_root  # noqa: F401  (fixtures in the real on-disk formats)
from unicorn.model import Unicorn

from .helpers import synthetic_data, tiny_checkpoint, tiny_model


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthetic_data(tmp_path_factory.mktemp("eval_synth") / "nmr")


@pytest.fixture(scope="session")
def shapenet_model() -> Unicorn:
    return tiny_model("shapenet")


@pytest.fixture(scope="session")
def real_model() -> Unicorn:
    return tiny_model("real")


@pytest.fixture(scope="session")
def real_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "real.pt", "real", epoch=7)
