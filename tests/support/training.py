"""Tiny training runs: overrides that make `experiment=synthetic` a run of seconds, composing and building it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import lightning as L

from tests.support.forked import run_command
from unicorn.cli import train

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


def compose_config(overrides: list[str]):
    """The composed (unvalidated) training config for ``overrides``."""
    from hydra import compose, initialize_config_dir

    from unicorn.config.schema import store_schema
    from unicorn.resources import config_dir

    store_schema()  # train.yaml's defaults list starts with the schema
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("train", overrides=overrides)


def build_run(tmp_path: Path, *overrides: str):
    """A built (not yet trained) tiny run writing into ``tmp_path``."""
    from unicorn.lit.run import build

    return build(compose_config([*TINY, f"paths.output_dir={tmp_path}", *overrides]))


def unicorn_train(
    *args: str, cwd: Path, timeout: int = 240, fresh: bool = False, entry: str | None = None
) -> subprocess.CompletedProcess:
    """``unicorn-train ARGS`` in ``cwd`` (one thread, one-line errors), its output captured.

    The command is a new process forked from a server that imported torch and Lightning once
    (:mod:`tests.support.forked`), running ``entry`` (default ``unicorn.cli.train:main``; a test may name a ``main``
    of its own); ``fresh=True`` starts a new interpreter, ``python -m unicorn.cli.train``, which runs the real entry
    point only.
    """
    if fresh and entry is not None:
        raise ValueError("unicorn_train: fresh=True runs python -m unicorn.cli.train; it takes no entry")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    if not fresh:
        argv = [train.__file__, *args]  # what sys.argv holds under python -m
        return run_command(entry or "unicorn.cli.train:main", argv, cwd=cwd, env=env, timeout=timeout)
    return subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def error_lines(stderr: str) -> list[str]:
    """stderr without Lightning's start-up notes (``INFO: GPU available...``)."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith("INFO: ")]


class LossRecorder(L.Callback):
    """The loss terms each iteration's training step returned, and the device the module trained on."""

    def __init__(self) -> None:
        self.rows: list[dict[str, float]] = []
        self.devices: set[str] = set()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.rows.append({name: float(value) for name, value in outputs.items()})
        self.devices.add(next(pl_module.parameters()).device.type)


class StateBefore(L.Callback):
    """Records the module's state dict as iteration ``step`` starts (after the schedule's callbacks ran)."""

    def __init__(self, step: int) -> None:
        self.step, self.state = step, None

    def on_train_batch_start(self, trainer, pl_module, *args):
        if trainer.global_step == self.step:
            self.state = {k: v.detach().clone() for k, v in pl_module.state_dict().items()}


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every path under ``folder`` (hidden ones included), with the bytes of each file."""
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None for p in sorted(folder.rglob("*"))}
