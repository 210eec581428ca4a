"""``unicorn-train``: the Hydra application that trains UNICORN.

Examples::

    unicorn-train                                           # no arguments: +experiment=synthetic, the offline default
    unicorn-train +experiment=cub trainer=gpu dataset.root=/data/cub_200
    unicorn-train +experiment=cub ckpt_path=outputs/cub/runs/<time>/checkpoints/last.ckpt
    unicorn-train -m +experiment=synthetic seed=1,2,3       # a sweep, one run directory per job
    unicorn-train --cfg job +experiment=cub                 # print the composed config, train nothing
    unicorn-train --help                                    # what it does, the groups, examples; also --version

``+experiment=NAME`` and ``experiment=NAME`` are the same command (:func:`experiment_overrides`).

The configs are looked up where they ship: ``unicorn/conf`` inside an installed wheel, or the repository's
top-level ``conf/`` for an editable install; the directory is resolved from this file, never from the working
directory, and passed to Hydra as an absolute path. ``--config-dir``/``-cd`` adds a directory of your own
(e.g. ``-cd my_conf +experiment=mine`` with ``my_conf/experiment/mine.yaml``).

Every run writes to one directory (``outputs/<task_name>/runs/<time>`` or, for sweeps,
``outputs/<task_name>/multiruns/<time>/<job>``): ``.hydra/`` (composed config and overrides), ``config.yaml``
(the validated, resolved config), ``provenance.json`` (command, version, git commit), ``train.log``,
``tensorboard/``, ``csv/``, ``images/`` and ``checkpoints/``.
A folder that already holds a run is only trained in again to resume it (``ckpt_path=last``: the logs are
appended to) or with ``overwrite=true`` (its checkpoints and logs are deleted first).

Mistakes the user can fix (a bad value, a missing dataset or checkpoint, an unsafe checkpoint, a diverged run)
end the command with one line on stderr and exit status 2; a run folder that holds nothing yet is removed
again. ``--debug`` or ``HYDRA_FULL_ERROR=1`` shows the traceback.
"""

from __future__ import annotations

import builtins
import io
import logging
import os
import re
import shutil
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from unicorn.cli.allocator import tune_allocator
from unicorn.cli.errors import debug_requested, expected_error, one_line
from unicorn.resources import config_dir

__all__ = [
    "DEFAULT_EXPERIMENT",
    "Run",
    "build",
    "config_dir",
    "experiment_overrides",
    "fit",
    "hydra_argv",
    "main",
    "train",
]

#: what a bare ``unicorn-train`` runs: the offline default (procedural data, weights-free losses, CPU)
DEFAULT_EXPERIMENT = "synthetic"

log = logging.getLogger("unicorn.train")


def _route_lightning_logs() -> None:
    """Send Lightning's log records through the root logger's handlers only (each message printed once).

    Lightning gives its loggers a stderr handler of their own; under Hydra, whose root handlers also print to the
    console (and to train.log), every Lightning line would appear twice. Nothing changes without root handlers.
    """
    if not logging.getLogger().handlers:
        return
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            if isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler):
                logger.removeHandler(handler)
        logger.propagate = True


def _write_provenance(output_dir: Path, ckpt_path: str | None) -> None:
    """``<run>/provenance.json``: the command, resumed checkpoint, version and commit behind the run's metrics files
    (``heldout.csv``, ``csv/``, ``tensorboard/``); a resumed run keeps one record per start."""
    import json

    from hydra.core.hydra_config import HydraConfig

    from unicorn.io.provenance import command_line, provenance

    if int(os.environ.get("LOCAL_RANK", "0")) != 0 or int(os.environ.get("NODE_RANK", "0")) != 0:
        return  # DDP processes started by Lightning build the run again: one record per start
    if HydraConfig.initialized():
        command = command_line("unicorn-train", list(HydraConfig.get().overrides.task))
    else:  # built from Python (e.g. with Hydra's compose API)
        command = command_line(Path(sys.argv[0]).name, sys.argv[1:])
    path = output_dir / "provenance.json"
    starts = json.loads(path.read_text()) if path.is_file() else []
    path.write_text(json.dumps([*starts, provenance(command, ckpt_path)], indent=1))


@dataclass
class Run:
    """Everything :func:`build` assembles for one training run."""

    config: DictConfig
    trainer: Any
    module: Any
    data: Any
    output_dir: Path
    checkpoint_dir: Path
    ckpt_path: str | None


def build(cfg: DictConfig) -> Run:
    """Validate ``cfg`` and build the data, model, callbacks, loggers and trainer (nothing is trained).

    Raises:
        unicorn.config.ConfigError: an invalid config (unknown key, wrong type, inconsistent values).
    """
    # heavy imports here: `unicorn-train --help` and config errors stay fast
    import lightning as L
    from hydra.utils import instantiate
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from unicorn.config import ConfigError, model_config, validate
    from unicorn.io.checkpoints import init_weights
    from unicorn.io.run_folder import prepare_folder, resolve_ckpt
    from unicorn.io.serialization import check_checkpoint_path, remove_stale_temporaries
    from unicorn.lit import (
        AtomicCheckpointIO,
        CodeDiagnostics,
        HeldOutEvaluation,
        ImageLogger,
        PeriodicCheckpoint,
        ProgressBar,
        ResumeLogs,
        StageCallback,
        UnicornLitModule,
    )

    _route_lightning_logs()
    typed = validate(cfg)
    # checkpoints are meant to hold the state after the iteration's update: Lightning's hint does not apply
    warnings.filterwarnings("ignore", message=".*no pre-optimization state was saved.*")
    output_dir = Path(typed.paths.output_dir).expanduser().resolve()
    checkpoint_dir = output_dir / "checkpoints"
    ckpt_path = resolve_ckpt(typed.ckpt_path, checkpoint_dir)
    prepare_folder(output_dir, resume=typed.ckpt_path is not None, overwrite=typed.overwrite)
    output_dir.mkdir(parents=True, exist_ok=True)
    if checkpoint_dir.is_dir():
        for tmp in remove_stale_temporaries(checkpoint_dir):
            log.info("removed %s, a partial checkpoint of a killed run", tmp)
    (output_dir / "config.yaml").write_text(OmegaConf.to_yaml(typed, resolve=True))
    _write_provenance(output_dir, ckpt_path)

    L.seed_everything(typed.seed, workers=True, verbose=False)
    data = instantiate(typed.dataset, stream_seed=typed.seed, _convert_="all")
    module = UnicornLitModule(
        model_config(typed),
        optim=OmegaConf.to_container(typed.optim, resolve=True),
        alternation_period=typed.schedule.alternation_period,
        seed=typed.seed,
    )
    if typed.init_from is not None:
        info = init_weights(module.model, check_checkpoint_path(typed.init_from, "init_from"), typed.trust_checkpoint)
        log.info("init_from: starting from the weights of the %s", info.describe())

    s, cb = typed.schedule, typed.callbacks
    dims = OmegaConf.to_container(typed.model.stages, resolve=True)
    assert isinstance(dims, dict)
    if typed.model.background is None:
        dims.pop("background")
    callbacks: list[Any] = [
        StageCallback(
            dims=dims,
            milestones=list(s.milestones),
            curriculum=OmegaConf.to_container(s.curriculum, resolve=True),
            texture_averaging=OmegaConf.to_container(s.texture_averaging, resolve=True),
            mode=s.mode,
            plateau=OmegaConf.to_container(s.plateau, resolve=True),
        ),
        # keeps the `keep` latest periodic checkpoints ("step" is always a monitor candidate) plus last.ckpt
        PeriodicCheckpoint(
            dirpath=checkpoint_dir,
            filename="step={step:07d}",
            auto_insert_metric_name=False,
            every_n_train_steps=cb.checkpoint.every_n_steps,
            monitor="step",
            mode="max",
            save_top_k=cb.checkpoint.keep,
            save_last=cb.checkpoint.save_last,
        ),
        ResumeLogs(resume=typed.ckpt_path is not None),
    ]
    if typed.trainer.enable_progress_bar:
        # Lightning refuses a progress-bar callback with enable_progress_bar=False
        callbacks.append(ProgressBar(refresh_rate=cb.progress_bar_refresh_rate))
    if cb.images is not None:
        callbacks.append(ImageLogger(**OmegaConf.to_container(cb.images, resolve=True)))
    if cb.heldout is not None:
        callbacks.append(HeldOutEvaluation(**OmegaConf.to_container(cb.heldout, resolve=True)))
    if cb.diagnostics is not None:
        callbacks.append(CodeDiagnostics(**OmegaConf.to_container(cb.diagnostics, resolve=True)))
    callbacks += [instantiate(node) for node in cb.extra.values()]
    loggers = [instantiate(node) for node in typed.logger.values() if node is not None]

    trainer_kwargs = OmegaConf.to_container(typed.trainer, resolve=True)
    assert isinstance(trainer_kwargs, dict)
    if trainer_kwargs["val_check_interval"] is None:
        trainer_kwargs["limit_val_batches"] = 0
    try:
        trainer = L.Trainer(
            **trainer_kwargs,
            max_epochs=-1,  # training is counted in iterations (max_steps) over an endless stream
            check_val_every_n_epoch=None,
            use_distributed_sampler=False,  # the stream shards itself across ranks
            default_root_dir=str(output_dir),
            callbacks=callbacks,
            logger=loggers or False,
            plugins=[AtomicCheckpointIO(trust=typed.trust_checkpoint)],
        )
    except MisconfigurationException as err:  # e.g. accelerator=gpu on a machine without one
        t = typed.trainer
        raise ConfigError(
            f"trainer (accelerator={t.accelerator}, devices={t.devices}, strategy={t.strategy}): {err}"
        ) from err
    return Run(typed, trainer, module, data, output_dir, checkpoint_dir, ckpt_path)


def fit(run: Run) -> dict[str, float]:
    """Train a built run; returns the last values of the trainer's scalar callback metrics."""
    trainer, typed = run.trainer, run.config
    log.info("training %s for %d iterations in %s", typed.task_name, typed.trainer.max_steps, run.output_dir)
    trainer.fit(run.module, datamodule=run.data, ckpt_path=run.ckpt_path)
    if not trainer.interrupted and typed.callbacks.checkpoint.save_last:
        # the periodic checkpoints may not fall on the last iteration
        trainer.save_checkpoint(run.checkpoint_dir / "last.ckpt", weights_only=False)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    if typed.evaluate.enabled and not trainer.interrupted and trainer.is_global_zero:
        evaluate_run(run)
    return metrics


def evaluate_run(run: Run) -> Path:
    """The ``evaluate`` settings' evaluation of the trained model, in memory; returns the report folder.

    The metrics, ``report.html`` and ``report.png`` (inputs, reconstructions, meshes from new viewpoints) go to
    ``<run>/eval``; they record ``last.ckpt`` (the same weights) and the equivalent ``unicorn-eval`` command.
    """
    from unicorn.evaluation import EvalOptions, protocol_for
    from unicorn.evaluation.session import EvalTarget, evaluate_to_folder
    from unicorn.io.provenance import command_line, provenance

    e, d = run.config.evaluate, run.config.dataset
    checkpoint = run.checkpoint_dir / "last.ckpt"
    out = run.output_dir / "eval"
    argv = [str(checkpoint), f"--split={e.split}", f"--out={out}", f"--num-points={e.num_points}"]
    argv += [f"--icp-iterations={e.icp_iterations}", f"--batch-size={e.batch_size}"]
    argv += [f"--report-samples={e.report_samples}", f"--turntable-frames={e.turntable_frames}"]
    argv += [f"--mean-shape={e.mean_shape_iterations}"] + (["--own-mean-shape"] if e.own_mean_shape else [])
    argv += [f"--shape-points={e.shape_points}"]
    argv += [f"--max-images={e.max_images}"] if e.max_images is not None else []
    meta = {
        **provenance(
            command_line("unicorn-eval", argv),
            checkpoint if checkpoint.is_file() else None,
            produced_by=f"{command_line('unicorn-train', sys.argv[1:])} (evaluation after training)",
        ),
        "epoch": run.trainer.current_epoch,
        "step": run.trainer.global_step,
    }
    categories = OmegaConf.to_container(d.categories) if OmegaConf.is_config(d.categories) else d.categories
    target = EvalTarget(d.name, str(run.data.dataset_root()), e.split, categories, e.max_images)
    options = EvalOptions(
        protocol=protocol_for(d.name),
        batch_size=e.batch_size,
        num_points=e.num_points,
        icp_iterations=e.icp_iterations,
        average_texture=run.module.constant_mean_textures,
        report_samples=e.report_samples,
        own_mean_shape=e.own_mean_shape,
        shape_points=e.shape_points,
    )
    log.info("evaluating the trained model on the %s split", e.split)
    evaluate_to_folder(
        run.module.model,
        target,
        options,
        out,
        meta,
        mean_shape_iterations=e.mean_shape_iterations,
        turntable_frames=e.turntable_frames,
        title=f"{d.name} ({e.split}): {checkpoint.name}",
    )
    log.info("evaluation report: %s", out / "report.html")
    return out


def train(cfg: DictConfig) -> dict[str, float]:
    """Validate ``cfg``, build everything and train (:func:`build` then :func:`fit`)."""
    return fit(build(cfg))


#: set by main(): --debug was given
_DEBUG = False
#: set when Hydra hands the composed config to the task (errors before are Hydra's: composition, overrides)
_TASK_STARTED = False
#: where in the run folder the task writes Hydra's record of the run (``hydra.output_subdir``; None: nowhere)
_HYDRA_SUBDIR: str | None = ".hydra"


def _save_hydra_record(cfg: DictConfig, output_dir: Path) -> None:
    """Hydra's record of the run (``config.yaml``, ``hydra.yaml``, ``overrides.yaml`` in ``.hydra/``), as Hydra
    writes it, but only once the folder was accepted (Hydra itself would write it before the task, over the
    record of a run whose folder is then refused)."""
    from hydra.core.hydra_config import HydraConfig

    if _HYDRA_SUBDIR is None or not HydraConfig.initialized():
        return
    # a plain copy (Hydra's is read-only), interpolations kept as Hydra saves them
    hydra_cfg = OmegaConf.create(OmegaConf.to_container(HydraConfig.instance().cfg, resolve=False))
    hydra_cfg.hydra.output_subdir = _HYDRA_SUBDIR
    folder = output_dir / _HYDRA_SUBDIR
    folder.mkdir(parents=True, exist_ok=True)
    for name, node in (("config", cfg), ("hydra", hydra_cfg), ("overrides", hydra_cfg.hydra.overrides.task)):
        OmegaConf.save(node, folder / f"{name}.yaml")


def _task(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from unicorn.io.run_folder import holds_nothing

    global _TASK_STARTED
    _TASK_STARTED = True
    if isinstance(sys.stderr, _HeldStream):
        sys.stderr = sys.stderr.release()
    folders = {Path(HydraConfig.get().runtime.output_dir).resolve()}
    try:
        folders.add(Path(str(cfg.paths.output_dir)).expanduser().resolve())
    except Exception:  # an invalid paths group: validate() reports it
        pass
    empty_before = [f for f in folders if holds_nothing(f)]
    run = None
    try:
        run = build(cfg)
        _save_hydra_record(cfg, run.output_dir)
        fit(run)
    except Exception as err:
        if run is None or run.trainer.global_step == 0:
            # failed before the first iteration: no half-created run folder is left behind
            for folder in empty_before:
                if not any((folder / "checkpoints").glob("*.ckpt")):
                    shutil.rmtree(folder, ignore_errors=True)
        reported = expected_error(err)
        if reported is None or debug_requested(_DEBUG):
            raise  # a bug: Hydra prints the traceback, exit status 1
        print(f"unicorn-train: error: {one_line(reported)}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def experiment_overrides(overrides: list[str]) -> list[str]:
    """``overrides`` (command-line arguments or compose overrides) with ``+experiment=V`` written ``experiment=V``.

    ``conf/train.yaml`` ends its defaults list with ``experiment: null``: a placeholder after ``_self_``, so that the
    chosen experiment is merged last and overrides everything above it, and one that the compose API
    (``compose("train", overrides=["experiment=cub"])``) fills like any group. Hydra fills such an entry with
    ``experiment=NAME``; ``+experiment=NAME``, the form of Hydra's "Configuring Experiments" page (whose primary
    config has no entry), asks to append a second one, which Hydra refuses ("Multiple values for experiment").
    Rewriting the ``+`` form is the one change that makes both forms compose the same run, in single runs, sweeps
    (``-m +experiment=a,b``; the sweep value is kept as written) and with ``-cd DIR``, whose ``DIR/experiment/``
    presets join the same group. A ``train.yaml`` of your own in ``DIR`` replaces ours and must keep the
    ``experiment: null`` entry. Every other argument is returned unchanged.
    """
    prefix = "+experiment="
    return [arg[1:] if arg.startswith(prefix) else arg for arg in overrides]


def hydra_argv(argv: list[str]) -> list[str]:
    """The arguments handed to Hydra: :func:`experiment_overrides` of ``argv``, or ``experiment=synthetic`` (the
    offline default) when there are none."""
    return experiment_overrides(argv) if argv else [f"experiment={DEFAULT_EXPERIMENT}"]


class _HeldStream(io.TextIOBase):
    """Holds what is written to stderr until the task starts, so that Hydra's errors can be put on one line."""

    def __init__(self, stream: Any) -> None:
        self.stream, self.held, self.released = stream, io.StringIO(), False

    def write(self, text: str) -> int:
        # a handler created meanwhile may keep this object: after the release it writes through
        return self.stream.write(text) if self.released else self.held.write(text)

    def flush(self) -> None:
        if self.released:
            self.stream.flush()

    def release(self) -> Any:
        if not self.released:
            self.released = True
            self.stream.write(self.held.getvalue())
        return self.stream


def _hydra_subdir(args: list[str]) -> list[str]:
    """The arguments with Hydra's own writing of ``.hydra/`` turned off (the task writes it, see
    :func:`_save_hydra_record`); a ``hydra.output_subdir`` given by the user is kept for the task."""
    global _HYDRA_SUBDIR
    rest = []
    for arg in args:
        key, _, value = arg.partition("=")
        if key.lstrip("+~") == "hydra.output_subdir":
            _HYDRA_SUBDIR = None if value in ("", "null") or key.startswith("~") else value
        else:
            rest.append(arg)
    return [*rest, "hydra.output_subdir=null"]


#: the last line of a Python traceback: the exception's (qualified) name and message
_EXCEPTION_LINE = re.compile(r"^(?:[\w.]+\.)?(\w+): (.+)$")


def _hydra_failure(text: str) -> str | None:
    """The one line to print for what Hydra reported before the task ran, or None when it is a bug.

    Without a traceback it is a composition error (a misspelt override or group); with one, an expected failure
    only when the traceback ends in an ``OSError`` (e.g. the run folder cannot be created on a read-only disk).
    """
    lines = [line.strip() for line in text.splitlines() if line.strip() and "HYDRA_FULL_ERROR" not in line]
    if not any(line.startswith("Traceback (most recent call last)") for line in lines):
        return " ".join(lines) or "invalid command line"
    match = _EXCEPTION_LINE.match(lines[-1])
    cls = getattr(builtins, match.group(1), None) if match else None
    if match and isinstance(cls, type) and issubclass(cls, OSError):
        return match.group(2)
    return None


def main() -> None:
    """Console-script entry point (``unicorn-train``)."""
    global _DEBUG
    if "--debug" in sys.argv[1:]:
        sys.argv.remove("--debug")
        _DEBUG = True
    args = sys.argv[1:]
    if "--version" in args:
        from unicorn import __version__

        print(f"unicorn-train (unicorn3d) {__version__}")
        return
    if not args:
        print(
            f"unicorn-train: no arguments, running the offline default +experiment={DEFAULT_EXPERIMENT} "
            "(see unicorn-train --help)",
            file=sys.stderr,
            flush=True,
        )
    sys.argv[1:] = _hydra_subdir(hydra_argv(args))
    tune_allocator()
    held = None if debug_requested(_DEBUG) else _HeldStream(sys.stderr)
    if held is not None:
        sys.stderr = held
    try:
        hydra.main(config_path=str(config_dir()), config_name="train", version_base="1.3")(_task)()
    except SystemExit as exit:
        if held is None or _TASK_STARTED or not exit.code:
            raise
        sys.stderr = held.stream
        # Hydra's own report of an error before the task: one line, status 2, unless it is a bug
        line = _hydra_failure(held.held.getvalue())
        if line is None:
            sys.stderr.write(held.held.getvalue())
            raise
        print(f"unicorn-train: error: {line}", file=sys.stderr)
        raise SystemExit(2) from None
    finally:
        if isinstance(sys.stderr, _HeldStream):
            sys.stderr = sys.stderr.release()


if __name__ == "__main__":
    main()
