"""``unicorn-train``: the Hydra application that trains UNICORN.

Examples::

    unicorn-train                                           # no arguments: experiment=synthetic, the offline default
    unicorn-train experiment=cub trainer=gpu dataset.root=/data/cub_200
    unicorn-train experiment=cub ckpt_path=outputs/cub/runs/<time>/checkpoints/last.ckpt
    unicorn-train -m experiment=synthetic seed=1,2,3        # a sweep, one run directory per job
    unicorn-train --cfg job experiment=cub                  # print the composed config, train nothing
    unicorn-train --help                                    # what it does, the groups, examples; also --version

The configs are looked up where they ship: ``unicorn/conf`` inside an installed wheel, or the repository's
top-level ``conf/`` for an editable install; the directory is resolved from this file, never from the working
directory, and passed to Hydra as an absolute path. ``--config-dir``/``-cd`` adds a directory of your own
(e.g. ``-cd my_conf experiment=mine``).

Every run writes to one directory (``outputs/<task_name>/runs/<time>`` or, for sweeps,
``outputs/<task_name>/multiruns/<time>/<job>``): ``.hydra/`` (composed config and overrides), ``config.yaml``
(the validated, resolved config), ``provenance.json`` (command, version, git commit), ``train.log``,
``tensorboard/``, ``csv/``, ``images/`` and ``checkpoints/``.
"""

from __future__ import annotations

import logging
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

__all__ = ["DEFAULT_EXPERIMENT", "Run", "build", "config_dir", "fit", "hydra_argv", "main", "train"]

#: what a bare ``unicorn-train`` runs: the offline default (procedural data, weights-free losses, CPU)
DEFAULT_EXPERIMENT = "synthetic"

log = logging.getLogger("unicorn.train")


def config_dir() -> Path:
    """Absolute path of the shipped configs: ``unicorn/conf`` in a wheel, else the checkout's ``conf/``.

    Raises:
        FileNotFoundError: neither holds ``train.yaml``.
    """
    package = Path(__file__).resolve().parent.parent  # .../unicorn
    candidates = [package / "conf", package.parent.parent / "conf"]  # wheel; src/unicorn -> repository root
    for path in candidates:
        if (path / "train.yaml").is_file():
            return path
    raise FileNotFoundError(f"unicorn's configs (train.yaml) not found in {[str(p) for p in candidates]}")


def _resolve_ckpt(ckpt_path: str | None, checkpoint_dir: Path) -> str | None:
    """``None``, ``"last"`` (this run directory's last.ckpt if it exists) or an existing file."""
    if ckpt_path is None:
        return None
    if ckpt_path == "last":
        last = checkpoint_dir / "last.ckpt"
        if last.is_file():
            return str(last)
        log.info("ckpt_path=last: no %s yet, training from scratch", last)
        return None
    path = Path(ckpt_path).expanduser().resolve()
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: no checkpoint file at {path}")
    return str(path)


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
    from lightning.pytorch.callbacks import ModelCheckpoint

    from unicorn.config import model_config, validate
    from unicorn.lit import (
        AtomicCheckpointIO,
        CodeDiagnostics,
        HeldOutEvaluation,
        ImageLogger,
        IterationDataModule,
        ProgressBar,
        StageCallback,
        UnicornLitModule,
    )

    _route_lightning_logs()
    typed = validate(cfg)
    # checkpoints are meant to hold the state after the iteration's update: Lightning's hint does not apply
    warnings.filterwarnings("ignore", message=".*no pre-optimization state was saved.*")
    output_dir = Path(typed.paths.output_dir).expanduser().resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_dir = output_dir / "checkpoints"
    (output_dir / "config.yaml").write_text(OmegaConf.to_yaml(typed, resolve=True))
    ckpt_path = _resolve_ckpt(typed.ckpt_path, checkpoint_dir)
    _write_provenance(output_dir, ckpt_path)

    L.seed_everything(typed.seed, workers=True, verbose=False)
    data = IterationDataModule(instantiate(typed.dataset, _convert_="all"), seed=typed.seed)
    module = UnicornLitModule(
        model_config(typed),
        optim=OmegaConf.to_container(typed.optim, resolve=True),
        alternation_period=typed.schedule.alternation_period,
        seed=typed.seed,
    )

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
        ModelCheckpoint(
            dirpath=checkpoint_dir,
            filename="step={step:07d}",
            auto_insert_metric_name=False,
            every_n_train_steps=cb.checkpoint.every_n_steps,
            monitor="step",
            mode="max",
            save_top_k=cb.checkpoint.keep,
            save_last=cb.checkpoint.save_last,
        ),
        ProgressBar(refresh_rate=cb.progress_bar_refresh_rate),
    ]
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
    trainer = L.Trainer(
        **trainer_kwargs,
        max_epochs=-1,  # training is counted in iterations (max_steps) over an endless stream
        check_val_every_n_epoch=None,
        use_distributed_sampler=False,  # the stream shards itself across ranks
        default_root_dir=str(output_dir),
        callbacks=callbacks,
        logger=loggers or False,
        plugins=[AtomicCheckpointIO()],
    )
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
    """``unicorn-eval`` on the run's ``last.ckpt`` with the ``evaluate`` settings; returns the report folder.

    The metrics, ``report.html`` and ``report.png`` (inputs, reconstructions, meshes from new viewpoints) go
    to ``<run>/eval``.
    """
    from unicorn.cli import eval as eval_cli

    e = run.config.evaluate
    checkpoint = run.checkpoint_dir / "last.ckpt"
    if not checkpoint.is_file():
        raise FileNotFoundError(f"evaluate: no checkpoint at {checkpoint} (callbacks.checkpoint.save_last is off?)")
    out = run.output_dir / "eval"
    argv = [
        str(checkpoint),
        f"--split={e.split}",
        f"--out={out}",
        f"--num-points={e.num_points}",
        f"--icp-iterations={e.icp_iterations}",
        f"--batch-size={e.batch_size}",
        f"--report-samples={e.report_samples}",
        f"--turntable-frames={e.turntable_frames}",
        f"--mean-shape={e.mean_shape_iterations}",
    ]
    if e.max_images is not None:
        argv.append(f"--max-images={e.max_images}")
    log.info("evaluating %s on the %s split", checkpoint, e.split)
    from unicorn.io.provenance import command_line

    # the report records the equivalent unicorn-eval command, and the training command that ran it
    status = eval_cli.run(
        eval_cli.build_parser().parse_args(argv),
        command=command_line("unicorn-eval", argv),
        produced_by=f"{command_line('unicorn-train', sys.argv[1:])} (evaluation after training)",
    )
    if status != 0:
        raise RuntimeError(f"evaluation of {checkpoint} failed with status {status}")
    log.info("evaluation report: %s", out / "report.html")
    return out


def train(cfg: DictConfig) -> dict[str, float]:
    """Validate ``cfg``, build everything and train (:func:`build` then :func:`fit`)."""
    return fit(build(cfg))


def _task(cfg: DictConfig) -> None:
    from unicorn.config import ConfigError

    try:
        train(cfg)
    except ConfigError as err:
        # a readable one-liner instead of a traceback through Hydra
        log.error("%s", err)
        raise SystemExit(2) from None


def hydra_argv(argv: list[str]) -> list[str]:
    """The arguments handed to Hydra: ``experiment=synthetic`` (the offline default) when there are none."""
    return argv if argv else [f"experiment={DEFAULT_EXPERIMENT}"]


def main() -> None:
    """Console-script entry point (``unicorn-train``)."""
    args = sys.argv[1:]
    if "--version" in args:
        from unicorn import __version__

        print(f"unicorn-train (unicorn3d) {__version__}")
        return
    if not args:
        print(
            f"unicorn-train: no arguments, running the offline default experiment={DEFAULT_EXPERIMENT} "
            "(see unicorn-train --help)",
            file=sys.stderr,
            flush=True,
        )
    sys.argv[1:] = hydra_argv(args)
    hydra.main(config_path=str(config_dir()), config_name="train", version_base="1.3")(_task)()


if __name__ == "__main__":
    main()
