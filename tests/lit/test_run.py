"""The run's assembly: callbacks and loggers are the config's nodes, built by their ``_target_``, in a fixed order;
``model.compile`` compiles what ``fit`` names."""

from __future__ import annotations

import torch
from lightning.pytorch.callbacks import Timer

from tests.support.training import build_run
from unicorn.lit import (
    CodeDiagnostics,
    GracefulStop,
    ImageLogger,
    PeriodicCheckpoint,
    ProgressBar,
    ResumeLogs,
    StageCallback,
)
from unicorn.lit.loggers import CSVLogger
from unicorn.lit.run import fit
from unicorn.model import compile as compile_module
from unicorn.model.compile import networks


def test_callbacks_and_loggers_are_the_config_nodes(tmp_path) -> None:
    run = build_run(
        tmp_path,
        "callbacks.images={every_n_steps: 3, n_views: 2}",
        "+callbacks.extra.timer={_target_: lightning.pytorch.callbacks.Timer, duration: '00:01:00:00'}",
        "logger=csv",
        "callbacks.checkpoint.keep=3",
    )
    # Lightning moves checkpoint callbacks last
    kinds = [type(cb) for cb in run.trainer.callbacks]
    expected = [
        StageCallback, ResumeLogs, ProgressBar, ImageLogger, CodeDiagnostics, Timer, GracefulStop, PeriodicCheckpoint
    ]  # fmt: skip
    assert kinds == expected
    images = run.trainer.callbacks[3]
    assert (images.every_n_steps, images.n_views, images.n_images) == (3, 2, 8)  # n_images: the schema's default
    checkpoint = run.trainer.callbacks[-1]
    assert checkpoint.dirpath == str(tmp_path / "checkpoints") and checkpoint.save_top_k == 3
    assert checkpoint._every_n_train_steps == 4  # TINY's callbacks.checkpoint.every_n_steps
    assert [type(logger) for logger in run.trainer.loggers] == [CSVLogger]


def test_a_null_node_is_left_out(tmp_path) -> None:
    run = build_run(tmp_path, "callbacks.diagnostics=null", "trainer.enable_progress_bar=false")
    assert [type(cb) for cb in run.trainer.callbacks] == [StageCallback, ResumeLogs, GracefulStop, PeriodicCheckpoint]


def test_training_with_model_compile_compiles_the_networks_and_the_reconstruction_loss(
    synthetic_cache, tmp_path, monkeypatch
):
    compiled = []
    monkeypatch.setattr(compile_module, "compile_unavailable", lambda device: None)
    monkeypatch.setattr(torch.nn.Module, "compile", lambda self, **kwargs: compiled.append((self, kwargs)))
    run = build_run(tmp_path, "model.compile=reduce-overhead", "trainer.max_steps=1")
    fit(run)
    expected = [module for _, module in networks(run.module.model)]
    expected.append(run.module.objectives.steps["pose"].reconstruction)
    assert [module for module, _ in compiled] == expected
    assert all(kwargs == {"mode": "reduce-overhead"} for _, kwargs in compiled)
