"""A whole training run on CUDA through the CLI's build/fit (run where CUDA is)."""

from __future__ import annotations

import math

import pytest

from tests.support.training import build_run
from unicorn.lit.run import fit

pytestmark = pytest.mark.gpu


def test_training_iterations_on_cuda(synthetic_cache, tmp_path):
    run = build_run(tmp_path, "trainer.accelerator=gpu", "trainer.devices=1", "trainer.log_every_n_steps=1")
    fit(run)
    assert run.trainer.global_step == 8
    assert next(run.module.parameters()).is_cuda
    logged = run.trainer.logged_metrics
    assert logged and all(math.isfinite(float(v)) for v in logged.values())
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()
