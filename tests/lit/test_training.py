"""In-process training runs: stages and masks, the alternation, global_step, resume, the non-finite guard."""

from __future__ import annotations

import os
import signal
import warnings

import lightning as L
import pytest
import torch

from tests.support.training import LossRecorder, StateBefore, build_run
from unicorn.io.serialization import atomic_save
from unicorn.lit import NonFiniteLossError
from unicorn.lit.run import build, fit
from unicorn.model.encoder import Conv2d

POSE_ONLY = ("model.pose.",)
THREE_D_ONLY = ("model.shape.", "model.texture.", "model.scale.")


class Recorder(L.Callback):
    """Records, for every iteration, the stage state seen by the step and which parameters got gradients."""

    def __init__(self) -> None:
        self.rows: list[dict] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        model = pl_module.model
        self.rows.append(
            {
                "step": trainer.global_step,
                "stage": int(pl_module.stage),
                "dims": model.active_dims(),
                "translation": bool(model.pose.use_translation),
                "scale": bool(model.scale.use_scale),
                "elevation_roll": bool(model.pose.use_elevation_roll),
                "texture_p": float(pl_module.texture_average_p),
                "phase": pl_module.phase(trainer.global_step),
            }
        )

    def on_before_optimizer_step(self, trainer, pl_module, optimizer):
        named = list(pl_module.named_parameters())
        self.rows[-1]["got"] = {name for name, p in named if p.grad is not None}
        self.rows[-1]["nonzero"] = {name for name, p in named if p.grad is not None and bool(p.grad.abs().sum() > 0)}


def _last_texture_weight(module) -> torch.Tensor:
    # the zero-initialised last layer of the texture-code regressor gets a gradient from the first 3D step on
    return list(module.model.texture.regressor.parameters())[-2].detach()


def _has(names: set[str], prefixes: tuple[str, ...]) -> bool:
    return any(n.startswith(prefixes) for n in names)


def test_stages_masks_and_alternation(synthetic_cache, tmp_path):
    # the paper's stage-1 textures (2 dims, constant mean colours), which the synthetic experiment changes
    run = build_run(
        tmp_path,
        "schedule.curriculum.translation=1",
        "schedule.curriculum.elevation_roll=4",
        "model.stages.texture=[2,4,8,16]",
        "schedule.texture_averaging.constant_stages=1",
    )
    recorder = Recorder()
    run.trainer.callbacks.append(recorder)
    fit(run)
    rows = recorder.rows
    assert run.trainer.global_step == 8 and [r["step"] for r in rows] == list(range(8))  # one step = one iteration
    # milestones [3, 5, 7]; tiny dims shape 0/2/4/16, texture 2/4/8/16 (no background model in nmr mode)
    assert [r["stage"] for r in rows] == [1, 1, 1, 2, 2, 3, 3, 4]
    assert [r["dims"]["shape"] for r in rows] == [0, 0, 0, 2, 2, 4, 4, 16]
    assert [r["dims"]["texture"] for r in rows] == [2, 2, 2, 4, 4, 8, 8, 16]
    assert "background" not in rows[0]["dims"]
    assert [r["translation"] for r in rows[:3]] == [False, True, True]
    assert [r["scale"] for r in rows[:3]] == [False, False, True]
    assert [r["elevation_roll"] for r in rows] == [False] * 4 + [True] * 4
    # ShapeNet-style texture averaging: constant in stage 1, then p = 0.2 for the rest of the run
    assert [r["texture_p"] for r in rows] == pytest.approx([1.0] * 3 + [0.2] * 5)
    # the masks really zero the trailing code dimensions
    z = run.module.model.shape.code(torch.randn(2, 512))
    assert (z[:, 16:] == 0).all()
    # alternation: pose, 3D, pose, ...; each step's gradients reach its own branches only (idle: grad None)
    assert [r["phase"] for r in rows] == ["pose", "3d"] * 4
    for r in rows:
        got = r["got"]  # parameters whose gradient is not None (zero-initialised heads may give zeros)
        assert _has(got, ("model.encoders.",))  # the shared encoder learns in both steps
        if r["phase"] == "pose":
            assert _has(got, POSE_ONLY) and not _has(got, THREE_D_ONLY)
        else:
            assert _has(got, THREE_D_ONLY) and not _has(got, POSE_ONLY)
    assert any(_has(r["nonzero"], ("model.encoders.",)) for r in rows if r["phase"] == "3d")
    # the learning-rate drop at iteration 6 (x 0.2)
    assert run.trainer.optimizers[0].param_groups[0]["lr"] == pytest.approx(2e-4 * 0.2)
    assert (run.checkpoint_dir / "last.ckpt").is_file()


def test_idle_parameters_skip_vs_momentum(synthetic_cache, tmp_path):
    """skip: a 3D branch does not move in a pose step; momentum: it keeps moving along Adam's first moment."""
    moved = {}
    for mode in ("skip", "momentum"):
        # one Adam: with one per step kind the pose step's Adam holds no moments of the 3D branches to move by
        run = build_run(tmp_path / mode, f"optim.idle_params={mode}", "optim.adam_state=shared", "trainer.max_steps=3")
        snapshots: list[torch.Tensor] = []

        class Snap(L.Callback):
            def __init__(self, store: list[torch.Tensor]) -> None:
                self.store = store

            def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
                self.store.append(_last_texture_weight(pl_module).clone())

        run.trainer.callbacks.append(Snap(snapshots))
        fit(run)
        final = _last_texture_weight(run.module)
        # iteration 2 is a pose step: compare the texture branch before and after it
        moved[mode] = not torch.equal(snapshots[2], final)
    assert moved == {"skip": False, "momentum": True}


@pytest.mark.parametrize(
    "extra",
    [
        [],
        ["schedule.hue_shift=0.5"],
        ["schedule.roll_jitter=10", "schedule.shift_jitter=0.1"],
        ["model.loss.equivariance_weight=1"],
        # the 3D-step losses of iterations 1 and 3 are in the checkpoint at 4: the check at 8 needs all four
        ["schedule.mode=plateau", "schedule.plateau.window=2", "schedule.plateau.check_every=8",
         "schedule.plateau.patience=1", "schedule.plateau.min_steps=1", "schedule.plateau.threshold=1.0"],
        # the first run's last.ckpt written at the end of training, off the periodic steps (3)
        ["callbacks.checkpoint.every_n_steps=3"],
    ],
    ids=["plain", "hue-shift", "jitter", "equivariance", "plateau", "end-of-training"],
)  # fmt: skip
def test_resume_is_exact(synthetic_cache, tmp_path, extra):
    straight = build_run(tmp_path / "straight", *extra)
    fit(straight)
    first = build_run(tmp_path / "resumed", "trainer.max_steps=4", *extra)
    fit(first)
    second = build_run(tmp_path / "resumed", "ckpt_path=last", *extra)
    assert second.ckpt_path is not None
    fit(second)
    assert second.trainer.global_step == 8
    if "schedule.mode=plateau" in extra:
        assert int(straight.module.stage) == 2  # the stage ended at the check, in both runs (compared below)
    a, b = straight.module.state_dict(), second.module.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6, msg=key)
    mem_a, mem_b = straight.module.objectives.memory.state(), second.module.objectives.memory.state()
    for key in mem_a:
        torch.testing.assert_close(mem_a[key], mem_b[key], msg=key)
    opt_a = straight.trainer.optimizers[0].state_dict()
    opt_b = second.trainer.optimizers[0].state_dict()
    assert opt_a["param_groups"][0]["lr"] == opt_b["param_groups"][0]["lr"]
    for index, state in opt_a["state"].items():
        torch.testing.assert_close(state["exp_avg"], opt_b["state"][index]["exp_avg"], rtol=1e-5, atol=1e-7)


def test_validation_during_training_leaves_the_training_unchanged(synthetic_cache, tmp_path):
    """The sampled pose objective picks candidates from torch's global generator: a validation pass between two
    iterations (``trainer.val_check_interval``) must not draw from it, or the training after it changes."""
    losses = {}
    for name, every in (("plain", "null"), ("validated", "2")):
        run = build_run(tmp_path / name, "model.loss.pose_objective=sampled", f"trainer.val_check_interval={every}")
        recorder = LossRecorder()
        run.trainer.callbacks.append(recorder)
        fit(run)
        losses[name] = recorder.rows
    assert len(losses["plain"]) == 8
    assert losses["validated"] == losses["plain"]


def record_checkpoints(run) -> list[tuple[str, int]]:
    """The (file name, global step) of every checkpoint ``run`` writes, in order, filled as it trains."""
    io = run.trainer.strategy.checkpoint_io
    written, save = [], io.save_checkpoint

    def recorded(checkpoint, path, storage_options=None):
        written.append((os.path.basename(path), checkpoint["global_step"]))
        save(checkpoint, path, storage_options)

    io.save_checkpoint = recorded
    return written


class SignalDuring(L.Callback):
    """Sends the run's process SIGTERM ``count`` times during iteration ``at`` (0-based): the run stops after it
    (once), or at once (twice)."""

    def __init__(self, at: int, count: int = 1) -> None:
        self.at, self.count = at, count

    def on_train_batch_start(self, trainer, *args):
        if trainer.global_step == self.at:
            for _ in range(self.count):
                os.kill(os.getpid(), signal.SIGTERM)  # the run's handler


def test_a_resumed_run_replaces_the_last_checkpoint_a_signal_wrote(synthetic_cache, tmp_path):
    """The last.ckpt of a signal is the run's own: the resumed run replaces it instead of writing last-v1.ckpt."""
    from unicorn.errors import Interrupted
    from unicorn.io.serialization import load_checkpoint_file

    first = build_run(tmp_path, "callbacks.checkpoint.every_n_steps=100")
    first.trainer.callbacks.append(SignalDuring(2))
    with pytest.raises(Interrupted, match="after iteration 3"):
        fit(first)
    second = build_run(tmp_path, "callbacks.checkpoint.every_n_steps=100", "ckpt_path=last")
    fit(second)
    assert sorted(p.name for p in second.checkpoint_dir.iterdir()) == ["last.ckpt"]
    assert load_checkpoint_file(second.checkpoint_dir / "last.ckpt")["global_step"] == 8


def test_a_run_stopped_at_the_lr_drop_with_validation_resumes_exactly(synthetic_cache, tmp_path):
    """SIGTERM after iteration 6 (``optim.lr_drop_step``, between two validations), resumed in its folder: the
    weights, Adam's moments, the learning rate and the CSV log (training and validation rows) are those of a run
    never stopped."""
    import csv

    from unicorn.errors import Interrupted

    extra = ["trainer.val_check_interval=2", "logger=csv", "callbacks.diagnostics=null"]
    straight = build_run(tmp_path / "straight", *extra)
    fit(straight)
    first = build_run(tmp_path / "resumed", *extra)
    first.trainer.callbacks.append(SignalDuring(5))
    with pytest.raises(Interrupted, match="after iteration 6;"):
        fit(first)
    second = build_run(tmp_path / "resumed", "ckpt_path=last", *extra)
    fit(second)
    a, b = straight.module.state_dict(), second.module.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)
    opt_a, opt_b = (run.trainer.optimizers[0].state_dict() for run in (straight, second))
    assert opt_a["param_groups"][0]["lr"] == opt_b["param_groups"][0]["lr"] == pytest.approx(2e-4 * 0.2)
    for index, state in opt_a["state"].items():
        assert all(torch.equal(value, opt_b["state"][index][name]) for name, value in state.items())

    def rows(run):
        with open(run.output_dir / "csv" / "metrics.csv", encoding="utf-8", newline="") as f:
            return [{k: v for k, v in row.items() if v} for row in csv.DictReader(f)]

    logged = rows(straight)
    assert [row["step"] for row in logged if "val/rgb" in row] == ["1", "3", "5", "7"]
    assert rows(second) == logged


def test_a_second_signal_stops_at_once_with_the_signals_status(synthetic_cache, tmp_path):
    """Signalled twice, a run stops in the iteration under way with no checkpoint written for it, and says so with
    the signal's exit status (Lightning's own end of it is ``sys.exit(1)``, which reads as a crash)."""
    from unicorn.errors import Interrupted

    run = build_run(tmp_path, "callbacks.checkpoint.every_n_steps=2")
    run.trainer.callbacks.append(SignalDuring(2, count=2))
    ctrl_c = signal.getsignal(signal.SIGINT)
    with pytest.raises(
        Interrupted,
        match=r"^stopped by SIGTERM at once \(signalled twice\) during iteration 3: the same command with "
        r"ckpt_path=last in the same folder resumes from the last checkpoint written$",
    ) as err:
        fit(run)
    assert err.value.exit_status == 143
    assert signal.getsignal(signal.SIGINT) is ctrl_c  # Lightning leaves Ctrl-C ignored
    assert sorted(p.name for p in run.checkpoint_dir.iterdir()) == ["last.ckpt", "step=0000002.ckpt"]
    # before any checkpoint, the message does not point at one
    early = build_run(tmp_path / "early", "callbacks.checkpoint.every_n_steps=4")
    early.trainer.callbacks.append(SignalDuring(1, count=2))
    with pytest.raises(Interrupted, match=r"iteration 2: no checkpoint was written yet: the same command with ckpt"):
        fit(early)


def test_a_signal_swallowed_while_the_run_was_built_stops_it_before_its_first_iteration(synthetic_cache, tmp_path):
    from unicorn.errors import Interrupted, interrupt_on_signal

    with pytest.raises(Interrupted, match="^stopped by SIGTERM before the first iteration$"):
        with interrupt_on_signal("outside the training iterations"):
            run = build_run(tmp_path)
            try:  # as a logging handler's emit() does with any Exception
                os.kill(os.getpid(), signal.SIGTERM)
            except Exception:
                pass
            fit(run)
    assert run.stopper.steps_run == 0 and not run.checkpoint_dir.exists()


@pytest.mark.parametrize("every", [4, 3, 100], ids=["on-the-last-step", "off-it", "none-during-the-run"])
def test_each_checkpoint_of_a_run_is_written_once(synthetic_cache, tmp_path, every):
    """``last.ckpt`` of the final iteration is written once, whether or not a periodic save falls on it."""
    run = build_run(tmp_path, f"callbacks.checkpoint.every_n_steps={every}")
    written = record_checkpoints(run)
    fit(run)
    # a periodic save writes its file once, and last.ckpt is a second name of it
    expected = [(f"step={s:07d}.ckpt", s) for s in range(every, 9, every)]
    assert written == (expected if 8 % every == 0 else [*expected, ("last.ckpt", 8)])
    last = run.checkpoint_dir / "last.ckpt"
    assert torch.load(last, weights_only=True)["global_step"] == 8
    if 8 % every == 0:
        assert last.samefile(run.checkpoint_dir / "step=0000008.ckpt")


@pytest.mark.parametrize(
    ("every", "save_last", "at"),
    [(4, "true", 3), (4, "true", 7), (3, "true", 7), (3, "true", 4), (4, "false", 3), (3, "false", 7)],
    ids=["periodic", "periodic-last", "last", "between", "periodic-no-last", "last-no-last"],
)
def test_a_signal_writes_last_ckpt_of_its_iteration_once(synthetic_cache, tmp_path, every, save_last, at):
    """The ``last.ckpt`` of a signal is written once: not again by a periodic save of the same iteration, nor by the
    end of training when the signal came during the last iteration, with or without ``save_last``."""
    from unicorn.errors import Interrupted
    from unicorn.io.serialization import load_checkpoint_file

    run = build_run(
        tmp_path, f"callbacks.checkpoint.every_n_steps={every}", f"callbacks.checkpoint.save_last={save_last}"
    )
    run.trainer.callbacks.append(SignalDuring(at))
    written = record_checkpoints(run)
    stop = at + 1
    with pytest.raises(Interrupted, match=f"after iteration {stop};"):
        fit(run)
    keep_last = save_last == "true"
    expected = [(f"step={s:07d}.ckpt", s) for s in range(every, stop + 1, every)]  # last.ckpt: linked to them
    if stop % every != 0 or not keep_last:
        expected.append(("last.ckpt", stop))
    assert written == expected
    assert load_checkpoint_file(run.checkpoint_dir / "last.ckpt")["global_step"] == stop


@pytest.mark.parametrize("every", [3, 4])
def test_without_last_ckpt_the_final_iteration_is_a_step_checkpoint(synthetic_cache, tmp_path, every):
    """With ``save_last=false`` the 8 iterations end in a ``step=0000008.ckpt``, written once (not again where the
    periodic save just wrote it), so that the evaluation after training reads the final weights."""
    run = build_run(
        tmp_path,
        f"callbacks.checkpoint.every_n_steps={every}",
        "callbacks.checkpoint.save_last=false",
        "callbacks.checkpoint.keep=-1",
    )
    written = record_checkpoints(run)
    fit(run)
    assert written == [(f"step={s:07d}.ckpt", s) for s in sorted({*range(every, 9, every), 8})]
    assert sorted(p.name for p in run.checkpoint_dir.iterdir()) == [name for name, _ in written]


class BatchRecorder(L.Callback):
    """The images of every training batch as the loader gives them."""

    def __init__(self) -> None:
        self.images: list[torch.Tensor] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.images.append(batch["image"].clone())


def test_hue_shift_changes_what_both_steps_train_on(synthetic_cache, tmp_path, monkeypatch):
    run = build_run(tmp_path, "schedule.hue_shift=0.5", "trainer.max_steps=4")
    module, recorder, seen = run.module, BatchRecorder(), []
    forward = module.objectives.forward

    def spy(phase, model, images, **kwargs):
        seen.append((phase, images.detach().clone()))
        return forward(phase, model, images, **kwargs)

    monkeypatch.setattr(module.objectives, "forward", spy)
    run.trainer.callbacks.append(recorder)
    fit(run)
    assert [phase for phase, _ in seen] == ["pose", "3d", "pose", "3d"]
    for step, ((_, images), loaded) in enumerate(zip(seen, recorder.images, strict=True)):
        assert not torch.allclose(images, loaded)  # the synthetic objects are coloured: a hue shift shows
        torch.testing.assert_close(images, module.training_images(loaded, step))  # a pure function of the step
        torch.testing.assert_close(images.amax(1), loaded.amax(1), atol=1e-5, rtol=0)  # HSV value kept
    x = recorder.images[0]
    assert not torch.allclose(module.training_images(x, 0), module.training_images(x, 1))
    assert build_run(tmp_path / "off").module.training_images(x, 0) is x


def test_roll_shift_jitter_moves_what_both_steps_train_on(synthetic_cache, tmp_path, monkeypatch):
    run = build_run(tmp_path, "schedule.roll_jitter=10", "schedule.shift_jitter=0.1", "trainer.max_steps=2")
    module, recorder, seen = run.module, BatchRecorder(), []
    forward = module.objectives.forward

    def spy(phase, model, images, **kwargs):
        seen.append(images.detach().clone())
        return forward(phase, model, images, **kwargs)

    monkeypatch.setattr(module.objectives, "forward", spy)
    run.trainer.callbacks.append(recorder)
    fit(run)
    for step, (images, loaded) in enumerate(zip(seen, recorder.images, strict=True)):
        assert not torch.allclose(images, loaded, atol=1e-3)
        torch.testing.assert_close(images, module.training_images(loaded, step))  # a pure function of the step
    x = recorder.images[0]
    assert not torch.allclose(module.training_images(x, 0), module.training_images(x, 1))
    assert build_run(tmp_path / "off").module.training_images(recorder.images[0], 0) is recorder.images[0]


def test_resume_from_a_checkpoint_with_whole_kernel_moments(synthetic_cache, tmp_path):
    """Checkpoints written when layer 4 trained its whole 3 x 3 kernels at 32 px hold Adam moments of the whole
    kernels (zero on the taps that meet padding): resuming one continues exactly as from today's checkpoint."""
    first = build_run(tmp_path / "first", "trainer.max_steps=4")
    fit(first)
    today = first.checkpoint_dir / "last.ckpt"
    checkpoint = torch.load(today, map_location="cpu", weights_only=False)
    convs = {id(m.weight): m for m in first.module.model.modules() if isinstance(m, Conv2d) and m.taps is not None}
    assert convs, "the tiny run's encoder keeps no taps: the test would not test anything"
    params = list(first.module.model.parameters())  # one parameter group per optimizer in this run
    widened = 0
    for state in checkpoint["optimizer_states"]:
        for index, entry in state["state"].items():
            conv = convs.get(id(params[index]))
            if conv is None:
                continue
            top, left, h, w = conv.taps
            for key in ("exp_avg", "exp_avg_sq"):
                whole = torch.zeros_like(conv.kernel)
                whole[:, :, top : top + h, left : left + w] = entry[key]
                entry[key] = whole
                widened += 1
    assert widened
    older = tmp_path / "older.ckpt"
    atomic_save(checkpoint, older)  # sealed with its new content's digest, as the trainer writes checkpoints
    runs = {}
    for name, path in (("today", today), ("older", older)):
        runs[name] = build_run(tmp_path / name, f"ckpt_path={path}")
        fit(runs[name])
    a, b = runs["today"].module.state_dict(), runs["older"].module.state_dict()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_nonfinite_loss_stops_with_step_and_term(synthetic_cache, tmp_path, monkeypatch):
    run = build_run(tmp_path)
    step = run.module.objectives.steps["3d"]
    original = step.forward

    def broken(model, images, average_texture=False, iteration=None):
        out = original(model, images, average_texture, iteration)
        out["rgb"] = out["rgb"] * float("nan")
        out["total"] = out["total"] + out["rgb"]
        return out

    monkeypatch.setattr(step, "forward", broken)
    with pytest.raises(NonFiniteLossError, match=r"iteration 1 \(3d step\): rgb = nan"):
        fit(run)
    assert (run.checkpoint_dir / "nonfinite-step=1.ckpt").is_file()


def test_weights_an_update_blew_up_stop_as_a_nonfinite_step(synthetic_cache, tmp_path):
    # the first update at this rate leaves finite weights whose forward overflows: the renderer's input check sees it
    run = build_run(tmp_path, "optim.lr=1e30")
    with pytest.raises(NonFiniteLossError, match=r"iteration 1 \(3d step\): the prediction: verts contains NaN"):
        fit(run)
    assert (run.checkpoint_dir / "nonfinite-step=1.ckpt").is_file()


def test_nonfinite_checkpoint_is_the_state_before_the_failing_iteration(synthetic_cache, tmp_path, monkeypatch):
    from unicorn.io.serialization import load_checkpoint_file

    run = build_run(tmp_path)
    step, n = run.module.objectives.steps["3d"], 3  # iteration 3 is a 3D step
    original = step.forward

    def nan_at_n(model, images, average_texture=False, iteration=None):
        # the forward pass has updated the BatchNorm statistics
        out = original(model, images, average_texture, iteration)
        if run.trainer.global_step == n:
            out["rgb"] = out["rgb"] * float("nan")
            out["total"] = out["total"] + out["rgb"]
        return out

    monkeypatch.setattr(step, "forward", nan_at_n)
    before = StateBefore(n)  # added last: after the stage callback's changes at iteration n
    run.trainer.callbacks.append(before)
    with pytest.raises(NonFiniteLossError, match=rf"iteration {n} \(3d step\): rgb = nan"):
        fit(run)
    saved = load_checkpoint_file(run.checkpoint_dir / f"nonfinite-step={n}.ckpt")
    assert saved["global_step"] == n and before.state is not None
    state = saved["state_dict"]
    assert state.keys() == before.state.keys()
    assert any(k.endswith("running_var") for k in state)
    for key, value in state.items():
        assert torch.equal(value, before.state[key]), key


def test_missing_dataset_is_a_clear_error(tmp_path):
    from tests.support.training import compose_config

    cfg = compose_config(
        ["experiment=cub", f"paths.output_dir={tmp_path}", f"dataset.root={tmp_path / 'nothing'}", "logger=none"]
    )
    cfg.model.loss.perceptual = "structural"
    with pytest.raises(FileNotFoundError, match="CUB-200-2011 root not found at .*nothing"):
        build(cfg)  # before the model and the trainer are built
    assert not any(tmp_path.iterdir())


def test_adam_state_per_step(synthetic_cache, tmp_path):
    """per_step: the pose step's Adam holds moments of the pose heads only, the 3D step's of the 3D branches
    only, both of the shared encoder, with equal learning rates after the drop; a resumed run is exact."""
    straight = build_run(tmp_path / "straight", "optim.adam_state=per_step")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit(straight)
    # the 3D step's scheduler steps before its Adam at iteration 0, on purpose: torch's warning is not shown
    assert not [w for w in caught if "lr_scheduler.step()" in str(w.message)]
    pose_opt, opt_3d = straight.trainer.optimizers
    names = dict(enumerate(n for n, _ in straight.module.named_parameters()))

    def held(opt) -> set[str]:
        index = {id(p): i for i, p in enumerate(straight.module.parameters())}
        return {names[index[id(p)]] for p in opt.state if opt.state[p]}

    pose_names, names_3d = held(pose_opt), held(opt_3d)
    assert _has(pose_names, POSE_ONLY) and not _has(pose_names, THREE_D_ONLY)
    assert _has(names_3d, THREE_D_ONLY) and not _has(names_3d, POSE_ONLY)
    assert _has(pose_names, ("model.encoders.",)) and _has(names_3d, ("model.encoders.",))
    encoder = next(p for n, p in straight.module.named_parameters() if n.startswith("model.encoders."))
    # four pose and four 3D steps, each counted by its own Adam; different moments for the shared encoder
    assert int(pose_opt.state[encoder]["step"]) == 4 and int(opt_3d.state[encoder]["step"]) == 4
    assert not torch.equal(pose_opt.state[encoder]["exp_avg_sq"], opt_3d.state[encoder]["exp_avg_sq"])
    assert pose_opt.param_groups[0]["lr"] == opt_3d.param_groups[0]["lr"] == pytest.approx(2e-4 * 0.2)

    first = build_run(tmp_path / "resumed", "optim.adam_state=per_step", "trainer.max_steps=5")
    fit(first)
    second = build_run(tmp_path / "resumed", "optim.adam_state=per_step", "ckpt_path=last")
    fit(second)
    a, b = straight.module.state_dict(), second.module.state_dict()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6, msg=key)
    for opt_a, opt_b in zip(straight.trainer.optimizers, second.trainer.optimizers, strict=True):
        for p_a, p_b in zip(opt_a.state_dict()["state"].values(), opt_b.state_dict()["state"].values(), strict=True):
            torch.testing.assert_close(p_a["exp_avg"], p_b["exp_avg"], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    "branch, overrides", [("texture", ()), ("background", ("family=real",))], ids=["texture", "background"]
)
def test_branch_lr_scale(synthetic_cache, tmp_path, branch, overrides):
    """optim.<branch>_lr_scale: the branch (code regressor and generator) in its own group at lr x scale, every
    other parameter at lr, in each Adam; the first 3D step moves a weight of the branch by about its own lr (Adam)."""
    run = build_run(
        tmp_path, *overrides, "optim.adam_state=per_step", f"optim.{branch}_lr_scale=5", "trainer.max_steps=2"
    )
    module = getattr(run.module.model, branch)
    # the code regressor's zero-initialised last layer: the only weights of the branch with a gradient at first
    weight = [p for p in module.regressor.parameters() if p.dim() == 2][-1]
    before = weight.detach().clone()
    fit(run)
    own = {id(p) for p in module.parameters()}
    for opt in run.trainer.optimizers:
        rest, group = opt.param_groups
        assert {id(p) for p in group["params"]} == own
        assert not own & {id(p) for p in rest["params"]}
        assert len(rest["params"]) + len(group["params"]) == len(list(run.module.model.parameters()))
        assert group["lr"] == pytest.approx(5 * rest["lr"])
    # iteration 0 is a pose step (no gradient for the branch), iteration 1 the 3D step: Adam's first step is ~lr
    step = (weight.detach() - before).abs()
    lr = run.trainer.optimizers[1].param_groups[1]["lr"]
    assert step.max() == pytest.approx(lr, rel=0.05)


def test_both_lr_scales_make_three_groups(synthetic_cache, tmp_path):
    run = build_run(
        tmp_path,
        "family=real",
        "optim.texture_lr_scale=3",
        "optim.background_lr_scale=5",
        "trainer.max_steps=1",
    )
    fit(run)
    model = run.module.model
    for opt in run.trainer.optimizers:  # one per step kind (the experiment's adam_state=per_step)
        rest, texture, background = opt.param_groups
        assert {id(p) for p in texture["params"]} == {id(p) for p in model.texture.parameters()}
        assert {id(p) for p in background["params"]} == {id(p) for p in model.background.parameters()}
        n = len(rest["params"]) + len(texture["params"]) + len(background["params"])
        assert n == len(list(model.parameters()))
        assert (texture["lr"], background["lr"]) == (pytest.approx(3 * rest["lr"]), pytest.approx(5 * rest["lr"]))


def test_background_lr_scale_needs_a_background(tmp_path):
    with pytest.raises(ValueError, match="background_lr_scale=5.0 but the model has no background"):
        build_run(tmp_path, "optim.background_lr_scale=5")  # the shapenet family: no background model


def test_adam_state_is_checked(tmp_path):
    from unicorn.config.build import ConfigError

    with pytest.raises(ConfigError, match=r"^optim.adam_state must be one of \('shared', 'per_step'\), got 'both'$"):
        build_run(tmp_path, "optim.adam_state=both")


def test_validation_logs_reconstruction_error_and_mask_iou(synthetic_cache, tmp_path, monkeypatch):
    module = build_run(tmp_path).module.eval()
    logged: dict[str, float] = {}
    monkeypatch.setattr(module, "log", lambda name, value, **kw: logged.__setitem__(name, float(value)))
    images = torch.rand(3, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        pred = module.model.predict(images)
        rec, alpha = module.model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    silhouette = (alpha > 0.5).float()
    assert 0 < silhouette[0].sum() < silhouette[0].numel()
    # image 0: its own silhouette (IoU 1); image 1: the complement (IoU 0); image 2: both empty (IoU 1)
    masks = torch.stack([silhouette[0], 1 - silhouette[1], torch.zeros_like(silhouette[2])])
    monkeypatch.setattr(module.model, "render", lambda *a: (rec, torch.cat([alpha[:2], torch.zeros_like(alpha[2:])])))
    with torch.no_grad():
        module.validation_step({"image": images, "mask": masks, "has_mask": torch.ones(3, dtype=torch.bool)}, 0)
    assert logged["val/mask_iou"] == pytest.approx(2 / 3)
    assert logged["val/rgb"] == pytest.approx(float(((rec - images) ** 2).mean()), rel=1e-5)


def test_a_signal_while_training_ends_stops_before_the_evaluation(synthetic_cache, tmp_path):
    """A SIGTERM after the last iteration's boundary (while the final last.ckpt is written) ends the command with
    the signal's status and without the evaluation after training, which a pre-empted job has no time for."""
    from unicorn.errors import Interrupted

    run = build_run(tmp_path, "callbacks.checkpoint.every_n_steps=100", "evaluate.enabled=true")
    io = run.trainer.strategy.checkpoint_io
    save = io.save_checkpoint

    def signalled(checkpoint, path, storage_options=None):
        os.kill(os.getpid(), signal.SIGTERM)  # the run's handler: noted, the write goes on
        save(checkpoint, path, storage_options)

    io.save_checkpoint = signalled
    with pytest.raises(Interrupted, match=r"^stopped by SIGTERM after the last iteration \(8\), the training") as err:
        fit(run)
    assert err.value.exit_status == 143 and "the evaluation after training did not run" in str(err.value)
    assert torch.load(run.checkpoint_dir / "last.ckpt", weights_only=True)["global_step"] == 8
    assert not (run.output_dir / "eval").exists()
