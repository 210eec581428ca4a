"""Training steps without host reads (:mod:`unicorn.hostsync`): none recorded after the checked steps, the same
losses as the default steps, and the deferred finite-loss check.

The CPU oracle (:mod:`tests.support.syncs`) records what would wait for the device on CUDA; the CUDA twin runs the
same steps under ``torch.cuda.set_sync_debug_mode("error")``.
"""

from __future__ import annotations

import collections
import math
import os

import lightning as L
import pytest
import torch

from tests.support.syncs import outside, record_syncs
from tests.support.training import LossRecorder, StateBefore, build_run
from unicorn.lit.callbacks import ProgressBar
from unicorn.lit.run import fit


class StepSyncs(LossRecorder):
    """The syncs of each training step (``training_step`` only; the callbacks' logging reads are not steps'),
    and the terms each step returned."""

    def __init__(self) -> None:
        super().__init__()
        self.syncs: dict[int, list] = {}

    def on_train_start(self, trainer, pl_module):
        step_fn = pl_module.training_step

        def recorded(batch, batch_idx):
            with record_syncs(host_data=True) as rec:  # a tensor from host data is a copy the host waits for
                out = step_fn(batch, batch_idx)
            self.syncs[trainer.global_step - 1] = rec.syncs
            return out

        pl_module.training_step = recorded


def _train(tmp_path, sync_free: bool | None, *overrides: str) -> StepSyncs:
    # logging every 4 iterations: the iterations in between are plain steps
    run = build_run(tmp_path, "trainer.log_every_n_steps=4", "callbacks.checkpoint.every_n_steps=8", *overrides)
    run.module.sync_free = sync_free
    recorder = StepSyncs()
    run.trainer.callbacks.append(recorder)
    fit(run)
    return recorder


#: every term and augmentation that is off by default (tests/objectives/test_sync_free.py runs them on another device)
OPTIONAL = (
    "schedule.hue_shift=0.1", "schedule.roll_jitter=10", "schedule.shift_jitter=0.05",
    "model.loss.spacing_weight=0.1", "model.loss.flip_weight=0.1", "model.loss.equivariance_weight=0.1",
    "model.loss.viewpoint=renders",
)  # fmt: skip


@pytest.mark.parametrize(
    "overrides",
    # without the diagnostics' overflow counter, the step counts the renders' overflow itself
    [(), OPTIONAL, ("callbacks.diagnostics=null",)],
    ids=["default", "optional", "no-diagnostics"],
)
def test_steps_read_nothing_back_after_the_checked_ones(synthetic_cache, tmp_path, overrides):
    rec = _train(tmp_path, True, *overrides)
    assert len(rec.syncs) == 8
    # the checked steps (0, 1) read the inputs' values and the finite flag, the logging steps (3, 7) the deferred
    # flag, the rasterizers' needed sizes and the logged values; the others nothing
    for step in (0, 1):
        assert any(s.where.startswith("lit/finite.py") and "(now)" in s.where for s in rec.syncs[step]), step
    own_count = "callbacks.diagnostics=null" in overrides  # the step's own overflow count, read with the rest
    for step in (3, 7):
        left = outside(rec.syncs[step])
        assert any("(verify)" in s for s in left) and any("(grow_buffers)" in s for s in left), (step, left)
        assert any("render/overflow.py" in s for s in left) == own_count, (step, left)
        assert all("lit/" in s or "(grow_buffers)" in s or "render/overflow.py" in s for s in left), (step, left)
    for step in (2, 4, 5, 6):
        left = outside(rec.syncs[step])
        assert not left, (step, collections.Counter(left))


class IterationSyncs(L.Callback):
    """The syncs of each whole iteration, from its first hook to the next iteration's: the step with the callbacks,
    the progress bar, Lightning's bookkeeping and the loading of the next batch. First among the callbacks."""

    def __init__(self) -> None:
        self.syncs: dict[int, list] = {}
        self._open = None

    def _close(self, step: int) -> None:
        if self._open is not None:
            context, recorder = self._open
            context.__exit__(None, None, None)
            self.syncs[step], self._open = recorder.syncs, None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self._close(trainer.global_step - 1)
        context = record_syncs(host_data=True)
        self._open = (context, context.__enter__())

    def on_train_end(self, trainer, pl_module):
        self._close(trainer.global_step - 1)


def test_whole_iterations_read_nothing_back_between_the_logging_steps(synthetic_cache, tmp_path):
    # the hooks, the progress bar and Lightning's logging too: a progress-bar value logged as a tensor is read back
    # at every iteration, a Python number logged is copied to the device
    logging = ("trainer.log_every_n_steps=4", "callbacks.checkpoint.every_n_steps=8")
    run = build_run(tmp_path, *logging, "trainer.enable_progress_bar=true")
    run.module.sync_free = True
    rec = IterationSyncs()
    run.trainer.callbacks.insert(0, rec)
    fit(run)
    assert sorted(rec.syncs) == list(range(8))
    loading = ("data/", "lit/data.py")  # the next batch, made on the host (moved to the device without a wait)
    for step in (2, 4, 5, 6):
        left = outside(rec.syncs[step], loading)
        assert not left, (step, collections.Counter(left))
    assert any("(verify)" in s for s in outside(rec.syncs[3], loading))  # the logging steps read
    # the progress bar shows the module's host values: the stage and the loss read at the last logging step
    bar = next(cb for cb in run.trainer.callbacks if isinstance(cb, ProgressBar))
    shown = bar.get_metrics(run.trainer, run.module)
    assert shown["stage"] == 4 and math.isfinite(shown["loss"]), shown


class Stages(L.Callback):
    """The stage each iteration trained in, as the progress bar shows it. Last among the callbacks."""

    def __init__(self) -> None:
        self.stages: list[int] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.stages.append(pl_module.progress["stage"])


#: a plateau schedule checked every 4 iterations (the logging ones) that ends a stage at every check once the stage
#: has 2 x 1 3D-step losses and 2 iterations: with threshold 1 any positive loss counts as no improvement
PLATEAU = (
    "schedule.mode=plateau", "schedule.plateau.window=1", "schedule.plateau.check_every=4",
    "schedule.plateau.patience=1", "schedule.plateau.min_steps=2", "schedule.plateau.threshold=1.0",
)  # fmt: skip


def test_plateau_stages_read_the_device_on_their_check_iterations_only(synthetic_cache, tmp_path):
    run = build_run(tmp_path, "trainer.log_every_n_steps=4", "callbacks.checkpoint.every_n_steps=8", *PLATEAU)
    run.module.sync_free = True
    rec, stages = IterationSyncs(), Stages()
    run.trainer.callbacks.insert(0, rec)
    run.trainer.callbacks.append(stages)
    fit(run)
    loading = ("data/", "lit/data.py")
    for step in (2, 4, 5, 6):
        left = outside(rec.syncs[step], loading)
        assert not left, (step, collections.Counter(left))
    # the checks after iterations 3 and 7 each found the losses of iterations (1, 3) and (5, 7)
    assert stages.stages == [1, 1, 1, 1, 2, 2, 2, 2]
    assert int(run.module.stage) == 3


def test_default_steps_are_those_of_today(synthetic_cache, tmp_path):
    rec = _train(tmp_path, False)
    # every step reads its inputs' values and its finite flag
    assert all(any(s.where.startswith("lit/finite.py") for s in rec.syncs[step]) for step in range(8))


#: stage 2 (with the neighbour term) and the scale switch in iteration 5, between the logging iterations 3 and 7
BETWEEN_LOGGING = ("schedule.milestones=[5,6,7]", "schedule.curriculum.scale=5")


@pytest.mark.parametrize("overrides", [(), BETWEEN_LOGGING, PLATEAU], ids=["default", "stage-between-logs", "plateau"])
def test_sync_free_steps_give_the_default_losses(synthetic_cache, tmp_path, overrides):
    # float64: the sync-free steps pack the fragments into fixed-capacity buffers and swap neighbours over the whole
    # batch, masked, so some sums run in another order; float32 rounding, carried on by the updates and magnified
    # by a near-zero -log p, can reach 1e-5 relative after a few steps, while in float64 the paths agree to 1e-9
    default = _train(tmp_path / "default", False, "trainer.precision=64-true", *overrides)
    free = _train(tmp_path / "free", True, "trainer.precision=64-true", *overrides)
    for step, (a, b) in enumerate(zip(default.rows, free.rows, strict=True)):
        assert a.keys() == b.keys(), step
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-9, abs=1e-12), (step, name)


class SyncErrors(L.Callback):
    """Runs the training steps from ``start`` (None: the first after the checked ones), except the logging steps,
    under ``torch.cuda.set_sync_debug_mode("error")``: a host read in them raises."""

    def __init__(self, log_every: int, start: int | None = None) -> None:
        self.log_every, self.start = log_every, start
        self.plain: list[int] = []

    def on_train_start(self, trainer, pl_module):
        step_fn = pl_module.training_step

        def strict(batch, batch_idx):
            step = trainer.global_step
            start = pl_module.checked_steps if self.start is None else self.start
            plain = step >= start and (step + 1) % self.log_every != 0
            torch.cuda.set_sync_debug_mode("error" if plain else "default")
            try:
                out = step_fn(batch, batch_idx)
            finally:
                torch.cuda.set_sync_debug_mode("default")
            if plain:
                self.plain.append(step)
            return out

        pl_module.training_step = strict


@pytest.mark.gpu
@pytest.mark.parametrize("overrides", [(), OPTIONAL], ids=["default", "optional"])
def test_cuda_steps_do_not_sync(synthetic_cache, tmp_path, overrides):
    run = build_run(tmp_path, "trainer.log_every_n_steps=4", "trainer.accelerator=gpu", "trainer.devices=1", *overrides)
    errors = SyncErrors(4)
    run.trainer.callbacks.append(errors)
    fit(run)
    assert run.trainer.global_step == 8 and errors.plain == [2, 4, 5, 6]


@pytest.mark.gpu
def test_cuda_captured_steps_do_not_sync_and_give_the_eager_losses(synthetic_cache, tmp_path):
    # float64 and one pose candidate: no argmin tie that rounding decides (tests/lit/test_cuda.py); no neighbour
    # term: its bin draw comes from another random stream in a graph
    same = (
        "trainer.log_every_n_steps=4", "trainer.max_steps=12", "trainer.accelerator=gpu", "trainer.devices=1",
        "trainer.precision=64-true", "model.pose.n_azim=1", "model.loss.neighbor_weight=0",
    )  # fmt: skip
    runs = {}
    for name in ("eager", "captured"):
        run = build_run(tmp_path / name, *same)
        if name == "captured":
            # CUDA graphs of the traced step with the eager kernels (the cudagraphs backend: no code generation
            # to wait for); from iteration 6 on every step replays graphs recorded at iterations 4 and 5
            run.module.compile_step("cudagraphs")
            errors = SyncErrors(4, start=6)
            run.trainer.callbacks.append(errors)
        runs[name] = LossRecorder()
        run.trainer.callbacks.append(runs[name])
        fit(run)
        assert run.trainer.global_step == 12
    assert errors.plain == [6, 8, 9, 10]
    for step, (a, b) in enumerate(zip(runs["eager"].rows, runs["captured"].rows, strict=True)):
        assert a.keys() == b.keys(), step
        for name in a:
            assert b[name] == pytest.approx(a[name], rel=1e-6, abs=1e-9), (step, name)


@pytest.mark.parametrize(
    ("overrides", "signal", "found"),
    [
        ((), False, 7),
        # stage 2 from iteration 5: the neighbour term joins the 3D step's terms between the checks at 3 and 7
        (("schedule.milestones=[5,6,7]",), False, 7),
        # SIGTERM during iteration 5: its checkpoint is not written from the non-finite state
        ((), True, 5),
        # a second checkpoint callback saving after iteration 5 (off the logging steps): it verifies first
        ((), "checkpoint", 5),
    ],
    ids=["same-terms", "term-added", "signal", "extra-checkpoint"],
)
def test_deferred_finite_check_rolls_back_to_the_last_verified_state(
    synthetic_cache, tmp_path, monkeypatch, overrides, signal, found
):
    import signal as signals

    from unicorn.io.serialization import load_checkpoint_file
    from unicorn.lit import NonFiniteLossError

    run = build_run(tmp_path, "trainer.log_every_n_steps=4", *overrides)
    run.module.sync_free = True
    step, n = run.module.objectives.steps["3d"], 5  # iteration 5 is a 3D step, between the checks at 3 and 7
    original = step.forward

    def nan_at_n(model, images, average_texture=False, iteration=None):
        out = original(model, images, average_texture, iteration)
        if run.trainer.global_step == n:
            out["rgb"] = out["rgb"] * float("nan")
            out["total"] = out["total"] + out["rgb"]
            if signal is True:
                os.kill(os.getpid(), signals.SIGTERM)  # the run's handler: stop after this iteration
        return out

    monkeypatch.setattr(step, "forward", nan_at_n)
    before = StateBefore(4)  # the state verified at iteration 3
    run.trainer.callbacks.append(before)
    extra = tmp_path / "extra"
    if signal == "checkpoint":
        run.trainer.callbacks.append(L.pytorch.callbacks.ModelCheckpoint(extra, every_n_train_steps=6, save_top_k=-1))
    with pytest.raises(
        NonFiniteLossError, match=rf"iteration 5 \(3d step\), found at iteration {found}: rgb, total; .*step=4"
    ):
        fit(run)
    # last.ckpt is still the periodic one of iteration 3: no checkpoint holds the weights after iteration 5
    assert load_checkpoint_file(run.checkpoint_dir / "last.ckpt")["global_step"] == 4
    saved = load_checkpoint_file(run.checkpoint_dir / "nonfinite-step=4.ckpt")
    assert saved["global_step"] == 4 and before.state is not None
    state = saved["state_dict"]
    assert state.keys() == before.state.keys()
    for key, value in state.items():
        assert torch.equal(value, before.state[key]), key
    assert all(torch.isfinite(p).all() for p in run.module.parameters())  # rolled back in memory too
    assert not extra.exists() or not any(extra.iterdir())


@pytest.mark.parametrize("sync_free", [False, True], ids=["default", "sync-free"])
def test_overflow_warns_once_without_the_diagnostics(synthetic_cache, tmp_path, sync_free):
    """One face per pixel overflows: the run says so once, at the first iteration (default steps) or at the first
    read of the steps without host reads, which count the overflow on the device."""
    from unicorn.render import RenderOverflowWarning
    from unicorn.render import overflow as render_overflow

    run = build_run(tmp_path, "callbacks.diagnostics=null", "renderer.faces_per_pixel=1", "trainer.log_every_n_steps=4")
    run.module.sync_free = sync_free
    run.module.checked_steps = 0  # every step of the sync-free run without host reads, the first included
    render_overflow._WARNED.discard(1)  # the renders' own warning is said once per process
    with pytest.warns(RenderOverflowWarning) as said:
        fit(run)
    said = [str(w.message) for w in said if issubclass(w.category, RenderOverflowWarning)]
    assert len(said) == 1, said
    last = 3 if sync_free else 0  # the first read: the first logging step, or the first iteration
    assert said[0].startswith(f"renderer: in the training renders of iterations 0-{last}, "), said
    assert "diagnostics" not in said[0]
