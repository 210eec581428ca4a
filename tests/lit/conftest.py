"""Shared fixtures of the training tests: a tiny synthetic dataset and a small, fast training config."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.data.conftest import cub_root, p3d_root, synth_nmr  # noqa: F401  (fixtures in the real on-disk formats)

#: overrides that turn `experiment=synthetic` into a run of a few seconds on two CPU cores
TINY = [
    "experiment=synthetic",
    "dataset.categories=chair",
    "dataset.synthetic.n_models=5",
    "dataset.batch_size=4",
    "model.pose.n_azim=2",
    "model.loss.memory_size=16",
    "renderer.faces_per_pixel=4",
    "schedule.milestones=[3,5,7]",
    "schedule.curriculum.scale=2",
    "optim.lr_drop_step=6",
    "trainer.max_steps=8",
    "trainer.val_check_interval=null",
    "trainer.enable_model_summary=false",
    "trainer.log_every_n_steps=1",
    "callbacks.checkpoint.every_n_steps=4",
    "callbacks.images=null",
    "callbacks.heldout=null",
    "evaluate.enabled=false",
    "logger=none",
]


@pytest.fixture(scope="session")
def synthetic_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache holding the 5-model synthetic set at 32 px; ``UNICORN_CACHE`` points at it (also for subprocesses)."""
    from unicorn.data.synthetic import ensure_synthetic_dataset

    cache = tmp_path_factory.mktemp("unicorn_cache")
    ensure_synthetic_dataset(
        root=cache / "synthetic_32px", category="chair", mode="nmr", n_models=5, seed=0, image_size=32, progress=False
    )
    old = os.environ.get("UNICORN_CACHE")
    os.environ["UNICORN_CACHE"] = str(cache)
    yield cache
    if old is None:
        os.environ.pop("UNICORN_CACHE", None)
    else:
        os.environ["UNICORN_CACHE"] = old


def compose_config(overrides: list[str]):
    """The composed (unvalidated) training config for ``overrides``."""
    from hydra import compose, initialize_config_dir

    from unicorn.resources import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("train", overrides=overrides)


def build_run(tmp_path: Path, *overrides: str):
    """A built (not yet trained) tiny run writing into ``tmp_path``."""
    from unicorn.cli.train import build

    return build(compose_config([*TINY, f"paths.output_dir={tmp_path}", *overrides]))
