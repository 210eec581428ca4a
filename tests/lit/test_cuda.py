"""A whole training run on CUDA through the CLI's build/fit, compared with the same run on the CPU (where CUDA is)."""

from __future__ import annotations

import lightning as L
import pytest
import torch

from tests.support.training import build_run
from unicorn.lit.run import fit

pytestmark = pytest.mark.gpu


class LossRecorder(L.Callback):
    """The loss terms each iteration's training step returned."""

    def __init__(self) -> None:
        self.rows: list[dict[str, float]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.rows.append({name: float(value) for name, value in outputs.items()})


def _losses(tmp_path, *overrides: str):
    run = build_run(tmp_path, "trainer.log_every_n_steps=1", *overrides)
    recorder = LossRecorder()
    run.trainer.callbacks.append(recorder)
    fit(run)
    assert run.trainer.global_step == 8 and len(recorder.rows) == 8
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()
    return run, recorder.rows


def _compare(cpu: list[dict[str, float]], gpu: list[dict[str, float]]) -> None:
    for step, (a, b) in enumerate(zip(cpu, gpu, strict=True)):
        assert a.keys() == b.keys(), step
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-3, abs=1e-5), (step, name)


@pytest.fixture
def full_float32(monkeypatch):
    """No TF32 convolutions or matrix products, so that a CUDA run differs from the CPU's by rounding only."""
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", False)


def test_training_iterations_on_cuda_match_the_cpu(synthetic_cache, tmp_path, full_float32):
    # the neighbour loss draws its viewpoint bins from the device's random stream: left out of the comparison
    same = "model.loss.neighbor_weight=0"
    cpu_run, cpu = _losses(tmp_path / "cpu", same)
    gpu_run, gpu = _losses(tmp_path / "gpu", same, "trainer.accelerator=gpu", "trainer.devices=1")
    assert next(gpu_run.module.parameters()).is_cuda and not next(cpu_run.module.parameters()).is_cuda
    _compare(cpu, gpu)


def test_training_iterations_on_cuda_with_the_neighbour_loss_match_the_cpu(synthetic_cache, tmp_path, full_float32):
    # one viewpoint bin: the bin drawn from the device's random stream is the same on both devices
    one_bin = "model.loss.n_bins=1"
    _, cpu = _losses(tmp_path / "cpu", one_bin)
    run, gpu = _losses(tmp_path / "gpu", one_bin, "trainer.accelerator=gpu", "trainer.devices=1")
    assert next(run.module.parameters()).is_cuda
    assert any(row.get("neighbor", 0) > 0 for row in gpu)  # the milestones [3, 5, 7] activate it
    _compare(cpu, gpu)
