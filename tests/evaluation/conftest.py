"""Fixtures of the evaluation tests: tiny models and checkpoints, the synthetic set, CUB / Pascal3D+ layouts."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.evaluation import synthetic_data, tiny_checkpoint, tiny_model
from unicorn.model import Unicorn


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
