"""One training run assembled from a composed config: the run folder, data, module, callbacks, loggers, trainer.

:func:`build` validates the config and builds everything (nothing is trained), :func:`fit` trains and, with
``evaluate.enabled``, evaluates the trained model (:func:`evaluate_run`). ``unicorn-train`` is these two calls
inside Hydra; tests and notebooks call them on a config from Hydra's compose API.

Callbacks and loggers are config nodes built by their ``_target_`` (``conf/callbacks``, ``conf/logger``); the run
adds the three that follow from other groups: the stage schedule (``schedule``, ``model.stages``), the log
rewinding of a resumed run (``ckpt_path``) and the progress bar (``trainer.enable_progress_bar``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from unicorn.checks import NonFiniteValueError
from unicorn.errors import Interrupted, interrupt_on_signal
from unicorn.io.run_folder import resume_hint

__all__ = [
    "Run",
    "build",
    "build_callbacks",
    "build_loggers",
    "check_run_folder",
    "evaluate_run",
    "fit",
    "is_first_process",
    "write_run_folder",
]

log = logging.getLogger("unicorn.train")


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
    stopper: Any  # the run's GracefulStop: signals, and the iterations this process ran


def build(cfg: DictConfig) -> Run:
    """Validate ``cfg`` and build the data, model, callbacks, loggers and trainer (nothing is trained).

    The run folder is checked first and written only once everything is built: a run refused here changes
    nothing on disk (:func:`check_run_folder`, :func:`write_run_folder`).

    Raises:
        unicorn.config.ConfigError: an invalid config (unknown key, wrong type, inconsistent values).
        unicorn.io.run_folder.RunFolderError: the folder holds a run this one may not replace.
    """
    from unicorn.config import validate
    from unicorn.lit.signals import ArmStopSignals, GracefulStop

    _route_lightning_logs()
    typed = validate(cfg)
    # checkpoints are meant to hold the state after the iteration's update: Lightning's hint does not apply
    warnings.filterwarnings("ignore", message=".*no pre-optimization state was saved.*")
    # Lightning's pytree helper builds torch's LeafSpec, which torch deprecates: nothing a user can change
    warnings.filterwarnings(
        "ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated", category=FutureWarning
    )
    output_dir, checkpoint_dir, ckpt_path, outdated = check_run_folder(typed)
    L.seed_everything(typed.seed, workers=True, verbose=False)
    with _config_nodes():
        data = instantiate(typed.dataset, stream_seed=typed.seed, _convert_="all")
        data.check_early()  # a missing dataset is said first: nothing else matters without it
        _check_protocol(data.name)
        # with ckpt_path=last, init_from starts the run, and a requeue of the same command resumes it
        init_from = typed.init_from if ckpt_path is None else None
        if typed.init_from is not None and init_from is None:
            log.info("init_from: not used: the run resumes from %s", ckpt_path)
        module = build_module(typed, init_from)
        stopper = GracefulStop(checkpoint_dir / "last.ckpt")
        # its handlers first, before any callback's set-up; itself a Checkpoint callback: after the periodic one
        callbacks = [ArmStopSignals(stopper), *build_callbacks(typed, checkpoint_dir), stopper]
        loggers = build_loggers(typed)
    trainer = build_trainer(typed, callbacks, loggers, output_dir)
    aside = write_run_folder(typed, output_dir, ckpt_path, outdated)
    if aside is not None:
        trainer.callbacks.append(DropAside(aside))
    return Run(typed, trainer, module, data, output_dir, checkpoint_dir, ckpt_path, stopper)


@contextlib.contextmanager
def _config_nodes() -> Iterator[None]:
    """Turn Hydra's failure to build a config node from a mistake in the config (a ``_target_`` that does not exist,
    arguments its class does not take) into a one-line ConfigError naming it; other failures keep their cause
    (a user error is reported as such, a bug with its traceback)."""
    from hydra.errors import InstantiationException

    from unicorn.config import ConfigError

    try:
        yield
    except InstantiationException as err:
        cause = err.__cause__
        misnamed = cause is None or isinstance(cause, ImportError | AttributeError)  # "Error locating target"
        if misnamed or (isinstance(cause, TypeError) and "argument" in str(cause)):
            text = str(err).replace(", set env var HYDRA_FULL_ERROR=1 to see chained exception", "")
            raise ConfigError(" ".join(text.split())) from err
        raise


def _no_tips(record: logging.LogRecord) -> bool:
    """Drop Lightning's advertisements (``💡 Tip: ...``), which say nothing of the run."""
    return not str(record.msg).startswith("💡 Tip")


def _route_lightning_logs() -> None:
    """Send Lightning's log records through the root logger's handlers only (each message printed once), without
    its tips.

    Lightning gives its loggers a stderr handler of their own; under Hydra, whose root handlers also print to the
    console (and to train.log), every Lightning line would appear twice. Nothing else changes without root handlers.
    """
    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")  # where Lightning's messages come from
    if _no_tips not in rank_zero.filters:
        rank_zero.addFilter(_no_tips)
    if not logging.getLogger().handlers:
        return
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            if isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler):
                logger.removeHandler(handler)
        logger.propagate = True


def check_run_folder(typed: DictConfig) -> tuple[Path, Path, str | None, list[Path]]:
    """Accept (or refuse) the run folder; reads only (:func:`unicorn.io.run_folder.plan_folder`).

    Returns:
        the run folder, its checkpoint folder, the checkpoint to resume from (None: a new run) and the earlier
        run's outputs that ``overwrite=true`` deletes.

    Raises:
        unicorn.io.run_folder.RunFolderError: a folder this run may not train in.
        unicorn.io.provenance.ProvenanceError: a ``provenance.json`` this run could not add its start to.
    """
    from unicorn.io.provenance import read_run_starts
    from unicorn.io.run_folder import plan_folder, resolve_ckpt

    output_dir = Path(typed.paths.output_dir).expanduser().resolve()
    _check_one_run_folder(output_dir)
    checkpoint_dir = output_dir / "checkpoints"
    ckpt_path = resolve_ckpt(typed.ckpt_path, checkpoint_dir, typed.callbacks.checkpoint.save_last)
    if not is_first_process():  # a DDP process Lightning started, after the first one accepted the folder
        return output_dir, checkpoint_dir, ckpt_path, []
    outdated = plan_folder(output_dir, typed.ckpt_path, ckpt_path, typed.overwrite)
    if ckpt_path is not None:
        check_resumed_settings(typed, Path(ckpt_path))
    read_run_starts(output_dir / "provenance.json")  # the run adds its start to them
    return output_dir, checkpoint_dir, ckpt_path, outdated


def _check_one_run_folder(output_dir: Path) -> None:
    """Under Hydra, refuse a ``paths.output_dir`` other than the folder Hydra made for the run (``hydra.run.dir``),
    where it writes ``train.log`` and ``.hydra/``: the run would be split between two folders, and the checks and
    the lock would cover only one.

    Raises:
        unicorn.config.ConfigError: names both folders.
    """
    from hydra.core.hydra_config import HydraConfig

    from unicorn.config import ConfigError

    if not HydraConfig.initialized():
        return
    made = Path(HydraConfig.get().runtime.output_dir).expanduser().resolve()
    if made != output_dir:
        raise ConfigError(
            f"paths.output_dir={output_dir} is not the run's folder {made}, where its log goes: choose the folder "
            "with hydra.run.dir=... (hydra.sweep.dir=... in a sweep) and leave paths.output_dir as it is"
        )


#: the optimisation settings a resumed run takes from its checkpoint (Adam's and the schedule's saved states
#: replace what the config builds), which a resume cannot change
RESUMED_OPTIM = (
    "lr", "betas", "eps", "weight_decay", "lr_drop_step", "lr_drop_gamma", "texture_lr_scale", "background_lr_scale",
    "adam_state",
)  # fmt: skip
#: the settings that say which data a run trains on: a resumed run keeps them, and its dataset's
#: :attr:`~unicorn.data.registry.DatasetSpec.data_options` (a moved ``dataset.root`` is a change it may make, with a
#: warning)
RESUMED_DATA = ("name", "categories", "img_size", "synthetic")
#: the settings a resume is expected to change (where it goes on, from what, for how long): not listed as changes
_RESUME_SETTINGS = ("ckpt_path", "overwrite", "trust_checkpoint", "paths", "trainer.max_steps")


def check_resumed_settings(typed: DictConfig, ckpt_path: Path) -> None:
    """Compare a resumed run's settings with the ``config.yaml`` of the run its checkpoint comes from: the
    optimisation settings the checkpoint holds (:data:`RESUMED_OPTIM`) and the data (:data:`RESUMED_DATA`) must be
    the same; any other change is logged, key by key (nothing when the checkpoint's run recorded no config). A
    checkpoint past ``trainer.max_steps`` is said in a warning: the run trains nothing.

    Raises:
        unicorn.config.ConfigError: a changed optimisation setting, which the resumed run would silently not use, or
            a change of the data the run trains on; in a sweep, a changed setting the job's command line sets (the
            sweep's jobs listed in another order, or with other values: each job resumes the folder of its number).
    """
    import yaml

    from unicorn.config import ConfigError
    from unicorn.io.run_folder import checkpoint_step, run_config, run_of_checkpoint

    step = checkpoint_step(ckpt_path)
    if step is not None and step > typed.trainer.max_steps:
        log.warning(
            "ckpt_path: %s is at iteration %d, past trainer.max_steps=%d: nothing is trained (raise "
            "trainer.max_steps to train on)",
            ckpt_path,
            step,
            typed.trainer.max_steps,
        )
    run_dir = run_of_checkpoint(ckpt_path)
    before = run_config(run_dir)
    if before is None:
        return
    recorded = run_dir / "config.yaml"
    changes = _differences(before, yaml.safe_load(recorded_config(typed)))
    said = lambda c: f"{c[0]} {c[1]!r} -> {c[2]!r}"  # noqa: E731
    under = lambda key, keys: any(key == k or key.startswith(f"{k}.") for k in keys)  # noqa: E731
    fixed = [c for c in changes if c[0] in {f"optim.{key}" for key in RESUMED_OPTIM}]
    if fixed:
        raise ConfigError(
            f"ckpt_path: a resumed run keeps its checkpoint's optimiser and schedule, and these settings differ from "
            f"its run's ({recorded}): {'; '.join(map(said, fixed))}; resume with the run's values, or start a new "
            "run from its weights with init_from=..."
        )
    data_keys = [*RESUMED_DATA, *(f"options.{key}" for key in _data_options(typed.dataset.name))]
    data = [c for c in changes if under(c[0], [f"dataset.{key}" for key in data_keys])]
    if data:
        raise ConfigError(
            f"ckpt_path: a resumed run trains on its run's data, and these settings differ from its run's "
            f"({recorded}): {'; '.join(map(said, data))}; resume with the run's data, or start a new run from its "
            "weights with init_from=..."
        )
    moved = _moved_folder(before, str(typed.paths.output_dir))
    shown = [c for c in changes if not under(c[0], _RESUME_SETTINGS) and not moved(c)]
    swept = [c for c in shown if under(c[0], _sweep_job_keys())]
    if swept:
        raise ConfigError(
            f"ckpt_path: this job of the sweep would resume {run_dir}, the run of a job with other values: "
            f"{'; '.join(map(said, swept))}; resume a sweep with the values it started with, in the same order "
            "(each job resumes the folder of its number), or sweep into a new hydra.sweep.dir"
        )
    if shown:
        log.warning("resuming with settings other than those in %s: %s", recorded, "; ".join(map(said, shown)))


def _data_options(dataset: str) -> tuple[str, ...]:
    """The options that say which data ``dataset`` reads (none for a dataset not registered here)."""
    from unicorn.data.registry import DATASETS

    return DATASETS.get(dataset).data_options if dataset in DATASETS else ()


def _moved_folder(before: Mapping[str, Any], output_dir: str) -> Callable[[tuple[str, Any, Any]], bool]:
    """Whether a change ``(key, was, now)`` is only the run folder's move: a path in the recorded run's folder
    (``before``'s ``paths.output_dir``) that names the same place in ``output_dir`` (a logger's ``save_dir``)."""
    paths = before.get("paths")
    old = paths.get("output_dir") if isinstance(paths, Mapping) else None

    def moved(change: tuple[str, Any, Any]) -> bool:
        _, was, now = change
        if not (isinstance(old, str) and isinstance(was, str) and isinstance(now, str)) or old == output_dir:
            return False
        return (was == old or was.startswith(f"{old}/")) and now == output_dir + was[len(old) :]

    return moved


def _sweep_job_keys() -> list[str]:
    """The keys this job of a sweep (``-m``) sets on the command line (``seed`` of ``seed=1``): what tells its run
    from the other jobs'; none outside a sweep."""
    from unicorn.io.run_folder import sweep_job_overrides

    return [key for key, override in sweep_job_overrides() if "=" in override]


def _differences(before: Any, now: Any, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """The keys whose values differ between two nested dicts, ``(dotted key, before, now)``; a key present in one
    only counts with None in the other."""
    if isinstance(before, dict) and isinstance(now, dict):
        found = []
        for key in sorted(set(before) | set(now), key=str):
            found += _differences(before.get(key), now.get(key), f"{prefix}{key}.")
        return found
    return [] if before == now else [(prefix.rstrip("."), before, now)]


class DropAside(L.Callback):
    """Delete the earlier run's outputs that ``overwrite=true`` set aside (``aside``) once the new run has done its
    first iteration; a run that fails before it puts them back (:class:`unicorn.io.run_folder.FolderChanges`)."""

    def __init__(self, aside: Path) -> None:
        self.aside: Path | None = aside

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        from unicorn.io.run_folder import drop_aside

        if self.aside is not None:
            drop_aside(self.aside)
            self.aside = None


def write_run_folder(typed: DictConfig, output_dir: Path, ckpt_path: str | None, outdated: list[Path]) -> Path | None:
    """Set ``outdated`` aside (an earlier run that ``overwrite=true`` replaces; see
    :func:`~unicorn.io.run_folder.set_aside`, deleted after the first iteration by :class:`DropAside`), then
    write ``config.yaml`` and ``provenance.json`` into the run folder (on the first process only); returns the
    folder holding what was set aside, or None."""
    from unicorn.io.run_folder import RUN_TABLES, set_aside
    from unicorn.io.serialization import remove_stale_temporaries

    if not is_first_process():
        return None  # DDP processes started by Lightning build the run again
    aside = set_aside(outdated, output_dir) if output_dir.is_dir() else None
    output_dir.mkdir(parents=True, exist_ok=True)
    # what the writers of a killed run left: in the run folder itself (which may be the user's) only its tables'
    for folder, names in ((output_dir / "checkpoints", None), (output_dir / "csv", None), (output_dir, RUN_TABLES)):
        if folder.is_dir():
            for tmp in remove_stale_temporaries(folder, names):
                log.info("removed %s, a partial file of a killed run", tmp)
    (output_dir / "config.yaml").write_text(recorded_config(typed), encoding="utf-8")
    _write_provenance(output_dir, ckpt_path)
    return aside


def recorded_config(typed: DictConfig) -> str:
    """The run's ``config.yaml``: the config resolved, its ``dataset.root`` absolute, so that ``unicorn-eval`` finds
    the data from any folder (a relative root is relative to the folder the run was started from)."""
    record = OmegaConf.create(OmegaConf.to_container(typed, resolve=True))
    root = record.dataset.root
    if root is not None and not os.path.isabs(os.path.expanduser(root)):
        record.dataset.root = os.path.abspath(root)
    return OmegaConf.to_yaml(record)


#: where a process's global rank is read from, in Lightning's order: torchrun's, Lightning's own launcher's (with
#: the node's), SLURM's (``srun``), LSF's
_RANK_VARIABLES = ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")


def is_first_process() -> bool:
    """Whether this is the process of global rank 0, which owns the run folder: the process the user started, not
    one that Lightning started for another DDP rank, nor another task of ``srun`` or another ``torchrun`` worker or
    node."""
    rank = next((os.environ[key] for key in _RANK_VARIABLES if os.environ.get(key) is not None), "0")
    nodes = [os.environ.get(key) or "0" for key in ("NODE_RANK", "GROUP_RANK")]
    return int(rank) == 0 and (os.environ.get("RANK") is not None or all(int(node) == 0 for node in nodes))


def _run_command() -> str:
    """The command that trains this run as the user gave it: ``unicorn-train``, the config folders given with
    ``--config-dir`` and the job's overrides (a sweep's values for this job; none of Hydra's own), or the Python
    command of a run built without Hydra."""
    from hydra.core.hydra_config import HydraConfig

    from unicorn.io.provenance import command_line

    if HydraConfig.initialized():
        hydra_cfg = HydraConfig.get()
        # a config folder given with --config-dir (-cd): the experiments it holds are not found without it
        folders = [
            source.path.removeprefix("file://")
            for source in hydra_cfg.runtime.config_sources
            if source.provider == "command-line" and source.schema == "file"
        ]
        options = [arg for folder in folders for arg in ("--config-dir", folder)]
        return command_line("unicorn-train", [*options, *hydra_cfg.overrides.task])
    return command_line(Path(sys.argv[0]).name, sys.argv[1:])  # built from Python (e.g. with Hydra's compose API)


def _write_provenance(output_dir: Path, ckpt_path: str | None) -> None:
    """``<run>/provenance.json``: the command, resumed checkpoint, version and commit behind the run's metrics files
    (``heldout.csv``, ``csv/``, ``tensorboard/``); a resumed run keeps one record per start."""
    from unicorn.io.provenance import provenance, read_run_starts

    path = output_dir / "provenance.json"
    starts = read_run_starts(path)  # checked before anything was written (check_run_folder)
    path.write_text(json.dumps([*starts, provenance(_run_command(), ckpt_path)], indent=1), encoding="utf-8")


def build_module(typed: DictConfig, init_from: str | None = None) -> Any:
    """The LightningModule of the validated config, from the weights of ``init_from`` when it names a file (the
    config's ``init_from`` where the run does not resume a checkpoint, :func:`build`)."""
    from unicorn.config import model_config
    from unicorn.io.checkpoints import init_weights
    from unicorn.io.serialization import check_checkpoint_path
    from unicorn.lit.module import UnicornLitModule

    module = UnicornLitModule(
        model_config(typed),
        optim=OmegaConf.to_container(typed.optim, resolve=True),
        alternation_period=typed.schedule.alternation_period,
        hue_shift=typed.schedule.hue_shift,
        roll_jitter=typed.schedule.roll_jitter,
        shift_jitter=typed.schedule.shift_jitter,
        seed=typed.seed,
    )
    if init_from is not None:
        info = init_weights(module.model, check_checkpoint_path(init_from, "init_from"), typed.trust_checkpoint)
        log.info("init_from: starting from the weights of the %s", info.describe())
    return module


def build_callbacks(typed: DictConfig, checkpoint_dir: Path) -> list[L.Callback]:
    """The run's callbacks, in this order: the stage schedule, ``callbacks.checkpoint`` (in ``checkpoint_dir``), the
    log rewinding of a resumed run, the progress bar, then ``callbacks.images``, ``heldout``, ``diagnostics`` and
    ``extra`` (each built by its ``_target_``; a null node is left out).

    Lightning runs checkpoint callbacks after all others, wherever they stand in the list.

    Raises:
        unicorn.config.ConfigError: a ``callbacks.extra`` node that does not build a Lightning ``Callback``.
    """
    from unicorn.config import ConfigError
    from unicorn.io.serialization import kind_of
    from unicorn.lit.callbacks import ProgressBar, StageCallback
    from unicorn.lit.loggers import ResumeLogs

    cb = typed.callbacks
    callbacks: list[L.Callback] = [
        StageCallback.from_config(typed.schedule, typed.model),
        instantiate(cb.checkpoint, dirpath=checkpoint_dir),
        ResumeLogs(resume=typed.ckpt_path is not None),
    ]
    if typed.trainer.enable_progress_bar:
        # Lightning refuses a progress-bar callback with enable_progress_bar=False
        callbacks.append(ProgressBar(refresh_rate=cb.progress_bar_refresh_rate))
    built = [instantiate(node) for node in (cb.images, cb.heldout, cb.diagnostics) if node is not None]
    for name, node in cb.extra.items():
        if node is None:
            continue
        extra = instantiate(node)
        if not isinstance(extra, L.Callback):
            raise ConfigError(
                f"callbacks.extra.{name}: {node.get('_target_')} built {kind_of(extra)}, not a Lightning Callback"
            )
        built.append(extra)
    return callbacks + built


def build_loggers(typed: DictConfig) -> list[Any]:
    """Every node of the ``logger`` group, built by its ``_target_`` (a null node is left out)."""
    return [instantiate(node) for node in typed.logger.values() if node is not None]


def build_trainer(typed: DictConfig, callbacks: list[L.Callback], loggers: list[Any], output_dir: Path) -> L.Trainer:
    """Lightning's trainer for an iteration-counted run over an endless, self-sharding stream.

    Raises:
        unicorn.config.ConfigError: trainer flags this machine cannot honour (e.g. ``accelerator=gpu`` without one).
    """
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from unicorn.config import ConfigError
    from unicorn.lit.checkpoint import AtomicCheckpointIO
    from unicorn.lit.signals import record_only_sigterm

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
    except (MisconfigurationException, ValueError, TypeError) as err:  # Lightning's checks raise all three
        t = typed.trainer
        raise ConfigError(
            f"trainer (accelerator={t.accelerator}, devices={t.devices}, strategy={t.strategy}): {err}"
        ) from err
    record_only_sigterm(trainer)  # no collective inside a signal handler (unicorn.lit.signals)
    return trainer


def _compile(run: Run) -> None:
    """``model.compile``: the networks compiled in place, or the steps' whole forward (``model.compile_scope``)."""
    from unicorn.model.compile import compile_available, compile_modules
    from unicorn.objectives import training_networks

    mode, device = run.config.model.compile, run.trainer.strategy.root_device
    if run.config.model.compile_scope == "networks":
        named = training_networks(run.module.model, run.module.objectives)
        if compile_modules([module for _, module in named], mode, device):
            log.info("compiled at their first call (torch.compile, mode %s): %s", mode, ", ".join(n for n, _ in named))
        return
    if not compile_available(device, "the steps", stacklevel=3, mode=mode):
        return
    run.module.compile_step(mode)
    log.info("the steps' forward compiled whole at the first step without host reads (torch.compile, mode %s)", mode)


def _note_unreached_stages(mode: str, milestones: list[int], max_steps: int) -> None:
    """Warn when ``trainer.max_steps`` ends a run with fixed milestones before its last stage: the code sizes of the
    stages it never reaches are not trained (a short trial of an experiment made for millions of iterations)."""
    reached = sum(m < max_steps for m in milestones)
    if mode != "fixed" or reached == len(milestones):
        return
    log.warning(
        "trainer.max_steps=%d ends the run in stage %d of %d: schedule.milestones=%s start the later stages after it "
        "(scale them with the run's length to train every stage)",
        max_steps,
        reached + 1,
        len(milestones) + 1,
        milestones,
    )


def _note_unreached_lr_drop(lr_drop_step: int | None, max_steps: int) -> None:
    """Warn when ``trainer.max_steps`` ends a run before its learning-rate drop (``optim.lr_drop_step``): the
    lowered rate never trains (a short trial of an experiment made for a longer schedule)."""
    if lr_drop_step is None or lr_drop_step < max_steps:
        return
    log.warning(
        "trainer.max_steps=%d ends the run before optim.lr_drop_step=%d: the learning rate is never lowered (scale "
        "the drop with the run's length, or set it to null)",
        max_steps,
        lr_drop_step,
    )


def fit(run: Run) -> dict[str, float]:
    """Train a built run; returns the last values of the trainer's scalar callback metrics.

    Raises:
        unicorn.errors.Interrupted: stopped by SIGTERM or SIGINT: in training at a step boundary
            (:class:`~unicorn.lit.signals.GracefulStop`), in the evaluation after training at once
            (:func:`~unicorn.errors.interrupt_on_signal`).
    """
    trainer, typed = run.trainer, run.config
    if typed.model.compile is not None:
        _compile(run)
    log.info("training %s for %d iterations in %s", typed.task_name, typed.trainer.max_steps, run.output_dir)
    _note_unreached_stages(typed.schedule.mode, list(typed.schedule.milestones), typed.trainer.max_steps)
    _note_unreached_lr_drop(typed.optim.lr_drop_step, typed.trainer.max_steps)
    ctrl_c = signal.getsignal(signal.SIGINT)
    try:
        trainer.fit(run.module, datamodule=run.data, ckpt_path=run.ckpt_path)
    except SystemExit as err:  # Lightning's end of a KeyboardInterrupt: the second signal (GracefulStop.at_once)
        signal.signal(signal.SIGINT, ctrl_c)  # Lightning ignores Ctrl-C from then on
        signum = run.stopper.at_once
        if signum is None:
            raise
        last, resume = run.checkpoint_dir / "last.ckpt", resume_hint(run.output_dir)
        then = (
            f"the same command with {resume} resumes from the last checkpoint written"
            if last.is_file() or any(run.checkpoint_dir.glob("step=*.ckpt"))
            else f"no checkpoint was written yet: the same command with {resume} trains it again from the start"
        )
        raise Interrupted(
            f"stopped by {signal.Signals(signum).name} at once (signalled twice) during iteration "
            f"{trainer.global_step + 1}: {then}",
            128 + signum,
        ) from err
    except NonFiniteValueError as err:  # a callback's render (pictures, held-out scores) of weights that blew up
        from unicorn.lit.finite import NonFiniteLossError

        raise NonFiniteLossError(
            f"the training diverged: the weights after iteration {trainer.global_step - 1} give non-finite values "
            f"({err}); train again, or resume from an earlier checkpoint, with a lower optim.lr"
        ) from err
    except SIGTERMException as err:  # Lightning's, at the end of the iteration GracefulStop saved, or elsewhere
        raise run.stopper.stopped or Interrupted(
            f"stopped by SIGTERM at iteration {trainer.global_step} (not at a step boundary: no checkpoint written)",
            128 + signal.SIGTERM,
        ) from err
    if run.stopper.stopped is not None:  # the signal came during the last iteration
        raise run.stopper.stopped
    if run.stopper.received is not None:  # after it, while training ended (its last.ckpt written)
        name = signal.Signals(run.stopper.received).name
        resume = resume_hint(run.output_dir)
        then = f"; the evaluation after training did not run: the same command with {resume} runs it"
        raise Interrupted(
            f"stopped by {name} after the last iteration ({trainer.global_step}), the training complete"
            + (then if typed.evaluate.enabled else ""),
            128 + run.stopper.received,
        )
    if not typed.callbacks.checkpoint.save_last:
        _drop_superseded_last(run.checkpoint_dir)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    if typed.evaluate.enabled and not trainer.interrupted and trainer.is_global_zero:
        where = f"during the evaluation after training; the same command with {resume_hint(run.output_dir)} ends it"
        with interrupt_on_signal(where):
            evaluate_run(run)
    return metrics


def _check_protocol(dataset: str) -> None:
    """Refuse a dataset whose evaluation protocol is unknown (a plugin's mistake) before training, not after it.

    Raises:
        unicorn.registry.UnknownNameError: names the dataset and its protocol, and lists the known ones.
    """
    from unicorn.evaluation import get_protocol, protocol_for
    from unicorn.registry import UnknownNameError

    try:
        get_protocol(protocol_for(dataset))
    except UnknownNameError as err:
        raise UnknownNameError(f"dataset {dataset!r}: {err}") from None


def _drop_superseded_last(checkpoint_dir: Path) -> None:
    """Remove the ``last.ckpt`` a signal wrote into a run with ``save_last=false`` once the run, resumed from it,
    has a newer ``step=<N>.ckpt``: otherwise it stays beside them, and whoever reads ``last.ckpt`` gets the weights
    of the iteration the signal stopped."""
    from unicorn.io.run_folder import checkpoint_step, step_checkpoints

    last = checkpoint_dir / "last.ckpt"
    step = checkpoint_step(last) if last.is_file() else None  # None: unreadable, left alone
    found = step_checkpoints(checkpoint_dir)
    if step is not None and found and found[-1][0] > step:
        log.info("removing %s (iteration %d, written by a signal): %s is newer", last, step, found[-1][1])
        last.unlink()


def _evaluated_before(metrics: Path, meta: dict[str, Any], target: Any) -> bool:
    """Whether ``metrics`` (an earlier evaluation's ``metrics.json``) evaluated the model of the same iteration
    on the same data with the same settings (its ``unicorn-eval`` command) and the same unicorn (version and
    commit): a resumed run that trained no further (a finished job of a resumed sweep) need not evaluate again."""
    try:
        found = json.loads(metrics.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    same = {
        **{key: meta.get(key) for key in ("command", "step", "unicorn_version", "git_commit")},
        "dataset": target.dataset,
        "root": target.root,
        "split": target.split,
        "categories": target.categories,
        "max_images": target.max_images,
        "dataset_options": target.dataset_options,
    }
    return isinstance(found, dict) and all(found.get(key) == value for key, value in same.items())


def evaluate_run(run: Run) -> Path:
    """The ``evaluate`` settings' evaluation of the trained model, in memory; returns the report folder.

    The metrics, ``report.html`` and ``report.png`` (inputs, reconstructions, meshes from new viewpoints) go to
    ``<run>/eval``; they record the run's newest checkpoint (``last.ckpt``, or with ``save_last=false`` the last
    ``step=<N>.ckpt``: the same weights) and the equivalent ``unicorn-eval`` command. A run
    resumed at its last iteration whose ``eval`` holds that iteration's evaluation with the same settings is not
    evaluated again.
    """
    from unicorn.config.schema import EvaluateConfig
    from unicorn.evaluation.session import (
        EvalTarget,
        eval_command,
        evaluate_to_folder,
        overflow_note,
        served_settings,
        settings_options,
    )
    from unicorn.io.provenance import provenance
    from unicorn.io.run_folder import newest_checkpoint

    d = run.config.dataset
    settings = served_settings(EvaluateConfig(**OmegaConf.to_container(run.config.evaluate, resolve=True)), d.name)
    skip_bad = d.on_error == "skip"  # the dataset's bad-file policy, as in training
    checkpoint = newest_checkpoint(run.checkpoint_dir) or run.checkpoint_dir / "last.ckpt"
    out = run.output_dir / "eval"
    meta = {
        **provenance(
            eval_command(checkpoint, out, settings, run.module.model.config["template"]["level"], skip_bad),
            checkpoint if checkpoint.is_file() else None,
            produced_by=f"{_run_command()} (evaluation after training)",
        ),
        "epoch": run.trainer.current_epoch,
        "step": run.trainer.global_step,
    }
    categories = OmegaConf.to_container(d.categories) if OmegaConf.is_config(d.categories) else d.categories
    options = OmegaConf.to_container(d.options) if OmegaConf.is_config(d.options) else dict(d.options or {})
    target = EvalTarget(
        d.name, str(run.data.dataset_root()), settings.split, categories, settings.max_images, d.on_error, options
    )
    if run.stopper.steps_run == 0 and _evaluated_before(out / "metrics.json", meta, target):
        log.info(
            "%s already holds the evaluation of this iteration's model (%d) with these settings: not evaluated "
            "again (delete it to evaluate again)",
            out,
            meta["step"],
        )
        return out
    log.info("evaluating the trained model on the %s split", settings.split)
    with overflow_note("the evaluation after training"):  # once, instead of the renderer's warning
        _, written = evaluate_to_folder(
            run.module.model,
            target,
            settings_options(settings, d.name, average_texture=run.module.constant_mean_textures),
            out,
            meta,
            mean_shape_iterations=settings.mean_shape_iterations,
            turntable_frames=settings.turntable_frames,
            title=f"{d.name} ({settings.split}): {checkpoint.name}",
        )
    if "html" in written:
        log.info("evaluation report: %s", written["html"])
    else:  # evaluate.report_samples=0: the metrics only (a report.html there is an earlier evaluation's)
        log.info("evaluation metrics: %s (no report: evaluate.report_samples=0)", written["csv"])
    return out
