"""The run's assembly: callbacks and loggers are the config's nodes, built by their ``_target_``, in a fixed order;
``model.compile`` compiles what ``fit`` names (``model.compile_scope``)."""

from __future__ import annotations

import signal

import lightning as L
import pytest
import torch
import torch.distributed as dist
import yaml
from lightning.pytorch.callbacks import Timer
from omegaconf import OmegaConf

from tests.support.training import build_run, compose_config
from unicorn.config.build import ConfigError, validate
from unicorn.lit import (
    ArmStopSignals,
    CodeDiagnostics,
    GracefulStop,
    ImageLogger,
    PeriodicCheckpoint,
    ProgressBar,
    ResumeLogs,
    StageCallback,
)
from unicorn.lit import compiled as compiled_module
from unicorn.lit.loggers import CSVLogger
from unicorn.lit.run import fit, recorded_config
from unicorn.model import compile as compile_module
from unicorn.model.compile import CompileWarning, networks


def test_callbacks_and_loggers_are_the_config_nodes(tmp_path) -> None:
    run = build_run(
        tmp_path,
        "callbacks.images={every_n_steps: 3, n_views: 2}",
        "+callbacks.extra.timer={_target_: lightning.pytorch.callbacks.Timer, duration: '00:01:00:00'}",
        "logger=csv",
        "callbacks.checkpoint.keep=3",
    )
    # the signal handlers first, before any callback's set-up; Lightning moves checkpoint callbacks last, in their
    # order: the signal's save comes after the periodic one
    kinds = [type(cb) for cb in run.trainer.callbacks]
    expected = [
        ArmStopSignals, StageCallback, ResumeLogs, ProgressBar, ImageLogger, CodeDiagnostics, Timer,
        PeriodicCheckpoint, GracefulStop,
    ]  # fmt: skip
    assert kinds == expected
    images = run.trainer.callbacks[4]
    assert (images.every_n_steps, images.n_views, images.n_images) == (3, 2, 8)  # n_images: the schema's default
    checkpoint = run.trainer.callbacks[-2]
    assert checkpoint.dirpath == str(tmp_path / "checkpoints") and checkpoint.save_top_k == 3
    assert checkpoint._every_n_train_steps == 4  # TINY's callbacks.checkpoint.every_n_steps
    assert [type(logger) for logger in run.trainer.loggers] == [CSVLogger]


def test_a_null_node_is_left_out(tmp_path) -> None:
    run = build_run(tmp_path, "callbacks.diagnostics=null", "trainer.enable_progress_bar=false")
    kinds = [type(cb) for cb in run.trainer.callbacks]
    assert kinds == [ArmStopSignals, StageCallback, ResumeLogs, PeriodicCheckpoint, GracefulStop]


@pytest.mark.parametrize("ours", [True, False], ids=["run", "lightning"])
def test_the_trainers_sigterm_handler_only_records_the_signal(tmp_path, monkeypatch, ours) -> None:
    # as Lightning ships it, its handler forwards the signal and, under DDP, broadcasts from inside the handler: a
    # rank waiting in another collective would never return (tests/cli/test_bad_inputs.py runs that case)
    run = build_run(tmp_path)
    connector = run.trainer._signal_connector if ours else L.Trainer(logger=False)._signal_connector
    collectives = []
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "broadcast", lambda *a, **k: collectives.append("broadcast"))
    monkeypatch.setattr(L.Trainer, "world_size", property(lambda self: 2))
    connector._sigterm_notifier_fn(signal.SIGTERM, None)
    assert connector.received_sigterm and collectives == ([] if ours else ["broadcast"])


def test_init_from_with_ckpt_path_last_starts_from_the_weights_and_the_same_command_resumes(
    synthetic_cache, tmp_path, caplog
):
    """A requeue-safe fine-tuning command: ``init_from`` starts the run where its folder holds no checkpoint, and the
    same command run again (a requeued job) resumes the run instead of starting it over from the weights."""
    source = build_run(tmp_path / "source", "trainer.max_steps=1")
    fit(source)
    weights = {k: v.clone() for k, v in source.module.model.state_dict().items()}
    command = (f"init_from={source.checkpoint_dir / 'last.ckpt'}", "ckpt_path=last")
    with caplog.at_level("INFO", logger="unicorn.train"):
        first = build_run(tmp_path / "tuned", *command, "trainer.max_steps=1")
    assert first.ckpt_path is None and "init_from: starting from the weights" in caplog.text
    assert all(torch.equal(v, weights[k]) for k, v in first.module.model.state_dict().items())
    fit(first)
    tuned = {k: v.clone() for k, v in first.module.model.state_dict().items()}
    caplog.clear()
    with caplog.at_level("INFO", logger="unicorn.train"):
        again = build_run(tmp_path / "tuned", *command, "trainer.max_steps=2")
    assert again.ckpt_path == str(tmp_path / "tuned" / "checkpoints" / "last.ckpt")
    assert "init_from: not used: the run resumes from" in caplog.text and "starting from the weights" not in caplog.text
    fit(again)
    assert again.trainer.global_step == 2 and again.stopper.steps_run == 1  # one more iteration, from the first's
    assert any(not torch.equal(tuned[k], weights[k]) for k in tuned)  # the first run trained


def test_training_with_model_compile_compiles_the_networks_and_the_reconstruction_loss(
    synthetic_cache, tmp_path, monkeypatch
):
    compiled = []
    monkeypatch.setattr(compile_module, "compile_unavailable", lambda device, mode="default": None)
    monkeypatch.setattr(torch.nn.Module, "compile", lambda self, **kwargs: compiled.append((self, kwargs)))
    run = build_run(tmp_path, "model.compile=reduce-overhead", "trainer.max_steps=1")
    fit(run)
    expected = [module for _, module in networks(run.module.model)]
    expected.append(run.module.objectives.steps["pose"].reconstruction)
    assert [module for module, _ in compiled] == expected
    assert all(kwargs == {"mode": "reduce-overhead"} for _, kwargs in compiled)


def test_model_compile_scope_step_compiles_the_steps_after_the_checked_ones(synthetic_cache, tmp_path, monkeypatch):
    calls = []

    def recording_compile(fn, **options):  # records, and runs the step eagerly (the compiled graphs: test_compiled)
        def run_step(kind, images, average_texture, iteration):
            calls.append((kind, iteration))
            return fn(kind, images, average_texture, iteration)

        return run_step

    monkeypatch.setattr(compile_module, "compile_unavailable", lambda device, mode="default": None)
    monkeypatch.setattr(compiled_module.torch, "compile", recording_compile)
    run = build_run(tmp_path, "model.compile=default", "model.compile_scope=step", "trainer.max_steps=4")
    fit(run)
    assert run.module.compiled_step is not None
    assert calls == [("pose", 2), ("3d", 3)]  # the first two steps of a process are checked, eagerly


def test_model_compile_scope_step_where_compile_cannot_run_warns_and_trains_eagerly(
    synthetic_cache, tmp_path, monkeypatch
):
    monkeypatch.setattr(
        compile_module, "compile_unavailable", lambda device, mode="default": "RuntimeError: no C++ compiler"
    )
    run = build_run(tmp_path, "model.compile=default", "model.compile_scope=step", "trainer.max_steps=2")
    with pytest.warns(CompileWarning, match="no C.. compiler.*the steps run eagerly"):
        fit(run)
    assert run.module.compiled_step is None and run.trainer.global_step == 2


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["model.compile_scope=graph"], "model.compile_scope must be one of"),
        (["model.compile=default", "model.compile_scope=step", "optim.sync_free=false"], "optim.sync_free is false"),
    ],
)
def test_model_compile_scope_is_checked(tmp_path, overrides, message) -> None:
    with pytest.raises(ConfigError, match=message):
        build_run(tmp_path, *overrides)


@pytest.mark.parametrize("root", ["datasets/cub_200", "/data/cub_200", "~/cub_200"])
def test_the_run_records_a_relative_dataset_root_as_absolute(tmp_path, monkeypatch, root) -> None:
    monkeypatch.chdir(tmp_path)  # the folder the run is started from
    typed = validate(compose_config(["experiment=cub", f"dataset.root='{root}'", f"paths.output_dir={tmp_path}/run"]))
    record = yaml.safe_load(recorded_config(typed))
    expected = str(tmp_path / root) if root == "datasets/cub_200" else root  # absolute (or home's) as given
    assert record["dataset"]["root"] == expected
    resolved = yaml.safe_load(OmegaConf.to_yaml(typed, resolve=True))
    resolved["dataset"]["root"] = expected
    assert record == resolved  # the rest is the resolved config as it was


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "+callbacks.extra.x={_target_:nonexistent.Foo}",
            r"^Error locating target 'nonexistent.Foo'\. full_key: callbacks",
        ),
        (
            "+callbacks.extra.x={_target_:lightning.pytorch.callbacks.Timer,bogus:1}",
            r"unexpected keyword argument 'bogus'.* full_key: callbacks.extra.x$",
        ),
        (
            "+callbacks.extra.rec={_target_:collections.OrderedDict}",
            r"^callbacks.extra.rec: collections.OrderedDict built an OrderedDict, not a Lightning Callback$",
        ),
        ("trainer.accelerator=bogus", r"^trainer \(accelerator=bogus, .*invalid accelerator name"),
        ("trainer.devices=[1,2]", r"^trainer \(accelerator=cpu, devices=\[1, 2\]"),
    ],
)
def test_a_node_the_run_cannot_build_is_one_config_error_and_writes_nothing(tmp_path, override, message) -> None:
    with pytest.raises(ConfigError, match=message) as info:
        build_run(tmp_path / "run", override)
    assert "\n" not in str(info.value) and not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "mode, max_steps, warned",
    [("fixed", 1000, "ends the run in stage 1 of 4"), ("fixed", 2500, "ends the run in stage 3 of 4"),
     ("fixed", 3001, None), ("plateau", 1000, None)],
)  # fmt: skip
def test_a_run_too_short_for_its_stages_is_told(caplog, mode: str, max_steps: int, warned: str | None) -> None:
    from unicorn.lit.run import _note_unreached_stages

    with caplog.at_level("WARNING", logger="unicorn.train"):
        _note_unreached_stages(mode, [1000, 2000, 3000], max_steps)
    messages = [r.getMessage() for r in caplog.records]
    if warned is None:
        assert not messages
    else:
        assert len(messages) == 1 and warned in messages[0] and "schedule.milestones=[1000, 2000, 3000]" in messages[0]


@pytest.mark.parametrize(
    "lr_drop_step, max_steps, warned", [(4400, 1000, True), (4400, 4400, True), (4400, 4401, False), (None, 10, False)]
)
def test_a_run_too_short_for_its_learning_rate_drop_is_told(caplog, lr_drop_step, max_steps, warned) -> None:
    from unicorn.lit.run import _note_unreached_lr_drop

    with caplog.at_level("WARNING", logger="unicorn.train"):
        _note_unreached_lr_drop(lr_drop_step, max_steps)
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ([f"trainer.max_steps={max_steps} ends the run before optim.lr_drop_step=4400: the learning "
                         "rate is never lowered (scale the drop with the run's length, or set it to null)"]
                        if warned else [])  # fmt: skip


@pytest.mark.parametrize(
    "env, first",
    [({}, True), ({"LOCAL_RANK": "1"}, False), ({"LOCAL_RANK": "0", "NODE_RANK": "1"}, False),
     ({"NODE_RANK": "1"}, False),  # Lightning's launcher's first process on the second node
     ({"SLURM_PROCID": "0", "SLURM_LOCALID": "0"}, True), ({"SLURM_PROCID": "1", "SLURM_LOCALID": "1"}, False),
     ({"SLURM_PROCID": "0", "LOCAL_RANK": "1"}, False),  # a process Lightning started inside an srun task
     ({"RANK": "0", "LOCAL_RANK": "0", "GROUP_RANK": "0"}, True),
     ({"RANK": "4", "LOCAL_RANK": "0", "GROUP_RANK": "1"}, False),  # torchrun's first worker of the second node
     ({"LOCAL_RANK": "0", "GROUP_RANK": "1"}, False)],
)  # fmt: skip
def test_the_first_process_is_global_rank_zero_whoever_launched_it(monkeypatch, env, first) -> None:
    from unicorn.lit.run import is_first_process

    for key in ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID", "SLURM_LOCALID", "JSM_NAMESPACE_RANK"):
        monkeypatch.delenv(key, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    assert is_first_process() is first


def test_a_resume_past_max_steps_says_that_nothing_is_trained(tmp_path, caplog) -> None:
    from unicorn.lit.run import check_resumed_settings

    typed = validate(compose_config(["experiment=synthetic", "trainer.max_steps=10", f"paths.output_dir={tmp_path}"]))
    ckpt = tmp_path / "step=0000044.ckpt"  # the iteration is read from the name
    ckpt.write_bytes(b"x")
    with caplog.at_level("WARNING", logger="unicorn.train"):
        check_resumed_settings(typed, ckpt)
    assert [r.getMessage() for r in caplog.records] == [
        f"ckpt_path: {ckpt} is at iteration 44, past trainer.max_steps=10: nothing is trained (raise "
        "trainer.max_steps to train on)"
    ]
    caplog.clear()
    typed = validate(compose_config(["experiment=synthetic", "trainer.max_steps=44", f"paths.output_dir={tmp_path}"]))
    check_resumed_settings(typed, ckpt)
    assert caplog.records == []  # a finished run resumed to end it: nothing to say


def test_a_dataset_whose_protocol_is_unknown_is_refused_before_training(monkeypatch) -> None:
    from unicorn.data.registry import DATASETS, DatasetSpec, dataset_spec, register_dataset
    from unicorn.lit.run import _check_protocol
    from unicorn.registry import UnknownNameError

    monkeypatch.setattr(DATASETS, "_entries", dict(DATASETS._loaded()))
    register_dataset("blobs", DatasetSpec(dataset_spec("folder").build, 5, "images_typo"))
    with pytest.raises(UnknownNameError, match=r"^dataset 'blobs': unknown protocol 'images_typo'; known: \["):
        _check_protocol("blobs")
    _check_protocol("folder")
