"""A whole training run on CUDA through the CLI's build/fit, compared with the same run on the CPU (where CUDA is).

Both run in float64 (``trainer.precision=64-true``) with one pose candidate (``model.pose.n_azim=1``). The pose
objective picks each image's best-reconstructing candidate by argmin, and in the first iterations, when the shape is
still a sphere, the candidates' losses tie to within rounding, in float64 too: which candidate each device picks is
rounding's choice, and the runs part from the first iteration on. The choice among several candidates on CUDA is
compared in ``tests/model/test_cuda.py``, whose randomised heads set the candidates' losses apart.
"""

from __future__ import annotations

import pytest

from tests.support.training import LossRecorder, build_run
from unicorn.lit.run import fit

pytestmark = pytest.mark.gpu


def _train(tmp_path, *overrides: str) -> LossRecorder:
    run = build_run(
        tmp_path, "trainer.log_every_n_steps=1", "trainer.precision=64-true", "model.pose.n_azim=1", *overrides
    )
    recorder = LossRecorder()
    run.trainer.callbacks.append(recorder)
    fit(run)
    assert run.trainer.global_step == 8 and len(recorder.rows) == 8
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()
    return recorder


def _compare(cpu: LossRecorder, gpu: LossRecorder) -> None:
    # the module's device while it trained: Lightning moves it back to the CPU when fit ends
    assert cpu.devices == {"cpu"} and gpu.devices == {"cuda"}
    for step, (a, b) in enumerate(zip(cpu.rows, gpu.rows, strict=True)):
        assert a.keys() == b.keys(), step
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-6, abs=1e-9), (step, name)


def test_training_iterations_on_cuda_match_the_cpu(synthetic_cache, tmp_path):
    # the neighbour loss draws its viewpoint bins from the device's random stream: left out of the comparison
    same = "model.loss.neighbor_weight=0"
    cpu = _train(tmp_path / "cpu", same)
    gpu = _train(tmp_path / "gpu", same, "trainer.accelerator=gpu", "trainer.devices=1")
    _compare(cpu, gpu)


def test_training_iterations_on_cuda_with_the_neighbour_loss_match_the_cpu(synthetic_cache, tmp_path):
    # one viewpoint bin: the bin drawn from the device's random stream is the same on both devices; it starts at 0
    # degrees since with one pose candidate the predicted rotations lie within the default 20 of each other
    one_bin = ("model.loss.n_bins=1", "model.loss.min_angle=0")
    cpu = _train(tmp_path / "cpu", *one_bin)
    gpu = _train(tmp_path / "gpu", *one_bin, "trainer.accelerator=gpu", "trainer.devices=1")
    assert any(row.get("neighbor", 0) > 0 for row in gpu.rows)  # the milestones [3, 5, 7] activate it
    _compare(cpu, gpu)
