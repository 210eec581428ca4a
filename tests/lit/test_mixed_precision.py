"""A tiny training run with ``trainer.precision=bf16-mixed`` on the CPU: Lightning's autocast around the manual
steps, the renderer in float32 inside it, and a checkpoint of float32 weights; and the float16 loss scaler's skipped
steps."""

from __future__ import annotations

import math

import lightning as L
import pytest
import torch

from tests.support.training import build_run
from unicorn.lit.run import fit


class StepRecorder(L.Callback):
    """Each iteration's total loss and whether its step ran under CPU autocast."""

    def __init__(self) -> None:
        self.losses: list[float] = []
        self.autocast: list[bool] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["total"]))

    def on_before_optimizer_step(self, trainer, pl_module, optimizer):
        # called from inside the manual step (opt.step), within the precision plugin's context
        self.autocast.append(torch.is_autocast_enabled("cpu"))


@pytest.mark.filterwarnings("ignore::unicorn.render.RenderOverflowWarning")
def test_bf16_mixed_run_trains_and_saves_float32_weights(synthetic_cache, tmp_path):
    run = build_run(tmp_path, "trainer.precision=bf16-mixed")
    recorder = StepRecorder()
    run.trainer.callbacks.append(recorder)
    fit(run)
    assert run.trainer.global_step == 8 and len(recorder.losses) == 8
    assert all(recorder.autocast) and all(math.isfinite(x) for x in recorder.losses)
    ckpt = tmp_path / "checkpoints" / "last.ckpt"
    assert ckpt.is_file()
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    floats = [v for v in state["state_dict"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float32 for v in floats)
    memory = state["unicorn"]["ranks"][0]["memory"]
    assert all(v is None or not v.is_floating_point() or v.dtype == torch.float32 for v in memory.values())


@pytest.mark.filterwarnings("ignore::unicorn.render.RenderOverflowWarning")
def test_float16_steps_whose_scaled_gradients_overflow_are_skipped_not_taken_for_divergence(synthetic_cache, tmp_path):
    # trainer.precision=16-mixed on CUDA: Lightning scales the loss with a GradScaler, whose scaled gradients
    # overflow by design now and then (it skips those steps and lowers the scale). The same plugin on the CPU, with a
    # scale so high that every step overflows: the run trains to its end, every update skipped.
    from lightning.pytorch.plugins.precision import MixedPrecision

    run = build_run(tmp_path, "trainer.max_steps=3")
    scaler = torch.amp.GradScaler("cpu", init_scale=1e38)
    run.trainer.strategy.precision_plugin = MixedPrecision("16-mixed", "cpu", scaler=scaler)
    before = {name: p.detach().clone() for name, p in run.module.named_parameters()}
    fit(run)
    assert run.trainer.global_step == 3
    assert scaler.get_scale() == pytest.approx(1e38 * 0.5**3, rel=1e-6)  # halved at each skipped step
    assert all(torch.equal(p, before[name]) for name, p in run.module.named_parameters())
