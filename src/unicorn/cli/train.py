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
appended to) or with ``overwrite=true`` (its checkpoints and logs are set aside, and deleted once the new run's first
iteration is done). One run trains in a folder
at a time (a lock file holding its pid); SIGTERM or SIGINT stops a run at the next step boundary with
``last.ckpt`` written, and the command exits with ``128 + signal`` (:mod:`unicorn.lit.signals`). Outside the
training iterations (building the run, the evaluation after training) a signal stops the command at once, with the
same status and a line that says where.

The run itself is assembled and trained by :mod:`unicorn.lit.run` (``build``, ``fit``); this module only turns the
command line into Hydra's, and :class:`~unicorn.cli.hydra_app.HydraApp` reports errors.

Mistakes the user can fix (a bad value, a missing dataset or checkpoint, an unsafe checkpoint, a diverged run)
end the command with one line on stderr and exit status 2; a run that fails before its first iteration leaves
its folder as it was (a folder it created is removed again, nothing the user made is touched). ``--debug`` or
``HYDRA_FULL_ERROR=1`` shows the traceback.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys

import unicorn.errors  # noqa: F401  records the signals ignored from the start (IGNORED_AT_START) first

if os.environ.get("LOCAL_RANK", "0") != "0":
    # a process Lightning started for another DDP rank runs this command line again. Until the run installs its
    # handlers (interrupt_on_signal), a Ctrl-C or SIGTERM sent to the whole process group would end it at once, and
    # Lightning would then SIGKILL the first process, which waits for it: the first process stops the run alone
    for _signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(_signum, signal.SIG_IGN)
    # and its C++ warnings (a lost connection to the first process, which has said why it stopped) stay quiet
    os.environ.setdefault("TORCH_CPP_LOG_LEVEL", "ERROR")
from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig, ListConfig

from unicorn.cli.allocator import tune_allocator
from unicorn.cli.errors import tolerate_closed_stdout
from unicorn.cli.hydra_app import HydraApp, NoteExistingFolders, entries_before, hydra_failure, swept_keys
from unicorn.errors import (
    Interrupted,
    UserError,
    defer_stop_signals,
    interrupt_on_signal,
    pending_interrupt,
    signals_held,
)
from unicorn.resources import config_dir

if TYPE_CHECKING:
    from unicorn.io.run_folder import FolderChanges

__all__ = [
    "DEFAULT_EXPERIMENT",
    "argument_note",
    "config_dir",
    "experiment_overrides",
    "hydra_argv",
    "hydra_failure",
    "main",
]

log = logging.getLogger("unicorn.train")

#: what a bare ``unicorn-train`` runs: the offline default (procedural data, weights-free losses, CPU)
DEFAULT_EXPERIMENT = "synthetic"

#: the running application (set by :func:`main`): :func:`_task` writes Hydra's record of the run through it
_app: HydraApp | None = None


def _task(cfg: DictConfig) -> None:
    """Lock the run folder, then build and train the run (:mod:`unicorn.lit.run`).

    A run that fails before its first iteration leaves its folders as it found them
    (:class:`~unicorn.io.run_folder.FolderChanges`): a folder this process created is removed, an existing one
    gets back the bytes it had. A run that fails later ends its ``train.log`` with how it ended. A second
    ``unicorn-train`` into a locked folder is refused and touches nothing.
    """
    from hydra.core.hydra_config import HydraConfig

    from unicorn.io.run_folder import FolderChanges, lock_folder
    from unicorn.lit.run import build, fit, is_first_process
    from unicorn.registry import load_plugins

    hydra_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    try:
        output_dir = Path(str(cfg.paths.output_dir)).expanduser().resolve()
    except Exception:  # an invalid paths group: validate() reports it
        output_dir = hydra_dir
    outside = "outside the training iterations: no checkpoint written"
    if not is_first_process():  # a DDP process Lightning started: the first one owns the folder
        _quiet_console()
        if _app is not None:
            _app.prog = "unicorn-train (another DDP process)"  # its own failures are told apart from the first's
        # a process Lightning started ignores signals until training (see the top of this module; GracefulStop then
        # stops every process at the same iteration): the first process alone stops the run before
        ignored = signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
        try:
            with contextlib.nullcontext() if ignored else interrupt_on_signal(outside):
                load_plugins()  # UNICORN_PLUGINS and the unicorn.plugins entry points: before the config is checked
                fit(build(cfg))
        except Interrupted as err:  # every process stops at the same point: the first one says so
            raise SystemExit(err.exit_status) from None
        except Exception as err:
            if _peer_failure(err) is not None:  # the first process ended: it says why
                raise SystemExit(1) from None
            raise
        return
    entries = {folder: entries_before(folder) for folder in (hydra_dir, output_dir)}
    # Hydra's folder, the only paths.output_dir build() accepts under Hydra (unicorn.lit.run._check_one_run_folder): a
    # folder elsewhere is never made, and a second signal's clean-up (put_back_job) covers the folder locked
    lock = lock_folder(hydra_dir)  # refused before anything is written when another run holds it
    top = NoteExistingFolders.created_top  # the outermost folder Hydra created above the run's
    changes = [FolderChanges(folder, names, top) for folder, names in entries.items()]
    run = None
    with interrupt_on_signal(outside):
        try:
            early = pending_interrupt(outside)  # a signal noted while the command set up (defer_stop_signals)
            if early is not None:
                raise early
            load_plugins()  # before the config is checked; a plugin that fails leaves the folders as they were
            _check_local_sweep(cfg)
            run = build(cfg)
            if _app is not None:
                _app.save_record(cfg, run.output_dir)
            fit(run)
        except Exception as caught:
            err = _peer_failure(caught) or caught
            if not isinstance(err, Interrupted):  # a signal's error that a reader turned into its own
                err = pending_interrupt(outside) or err
            if run is None or run.stopper.steps_run == 0:
                lock.release()
                _put_back(err, changes, output_dir)
            else:
                NoteExistingFolders.sweep = None  # the sweep's record now tells how this job ran
                err = _with_sweep_hint(err)
                _log_end(err)
            if err is not caught:
                raise err from caught
            raise
        else:
            NoteExistingFolders.sweep = None
        finally:
            lock.release()


class PeerProcessError(UserError, RuntimeError):
    """Another process of a DDP run ended (its own error, if any, is printed above by that process)."""


def _peer_failure(err: BaseException) -> PeerProcessError | None:
    """The one-line error for ``err`` when it says that another DDP process is gone (a closed connection of the
    process group), else None."""
    import torch.distributed as dist

    lost = ("Connection closed by peer", "Connection reset by peer", "Broken pipe", "Failed to recv")
    if not isinstance(err, getattr(dist, "DistError", ())) and not (
        isinstance(err, RuntimeError) and any(text in str(err) for text in lost)
    ):
        return None
    return PeerProcessError(
        f"another process of this DDP run ended (its message, if it had one, is above): {type(err).__name__}: "
        f"{' '.join(str(err).split())[:200]}"
    )


def _quiet_console() -> None:
    """Leave the console to the first process: the others print only errors there (their log files keep all)."""
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler):
            handler.setLevel(logging.ERROR)


def _check_local_sweep(cfg: DictConfig) -> None:
    """Refuse a sweep (``-m``) of DDP runs launched on this machine: Lightning starts each rank's process with the
    same command line, ``-m`` included, so every rank would run its own sweep (a launcher such as submitit starts
    each job's ranks instead).

    Raises:
        SweepError: the message says what to do instead.
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from unicorn.cli.errors import SweepError

    hydra = HydraConfig.get()
    launcher = str((hydra.launcher or {}).get("_target_", ""))
    strategy, devices = cfg.trainer.get("strategy"), cfg.trainer.get("devices")
    single = devices in (1, "1") or (isinstance(devices, list | ListConfig) and len(devices) == 1)
    if hydra.mode != RunMode.MULTIRUN or not launcher.endswith("BasicLauncher") or single:
        return
    if isinstance(strategy, str) and strategy.startswith("ddp"):
        raise SweepError(
            f"a sweep (-m) of DDP runs (trainer.strategy={strategy}, trainer.devices={devices}) cannot be launched "
            "on this machine: every DDP process would run the whole sweep; run the jobs one by one, with "
            "trainer.devices=1, or with a launcher that starts each job's processes (hydra/launcher=submitit_slurm)"
        )


def _put_back(err: Exception, changes: list[FolderChanges], output_dir: Path) -> None:
    """Put the folders of a run that failed with ``err`` before its first iteration back as they were; a signal
    (``err``, or one that comes meanwhile and waits for the folders) then raises :class:`Interrupted` saying so."""
    stop = err if isinstance(err, Interrupted) else None
    try:
        with signals_held():  # a signal now stops the command once the folders are back
            for change in changes:
                change.undo()
    except Interrupted as late:
        stop = late
    if stop is not None:
        name = signal.Signals(stop.exit_status - 128).name
        message = f"stopped by {name} before the first iteration; {output_dir} is left as it was"
        raise _with_sweep_hint(Interrupted(message, stop.exit_status)) from stop


def _with_sweep_hint(err: Exception) -> Exception:
    """A job of a sweep (``-m``) stopped by a signal: its message also says how the whole sweep goes on (the
    sweep's folder is named after the time it started, so a new command would start another), once a job of it
    kept its folder (:attr:`NoteExistingFolders.sweep` is None; a job stopped before its first iteration puts its
    own folder back, but not the jobs' before it). A sweep none of whose jobs kept a folder is removed again: the
    same command starts it anew."""
    from hydra.core.hydra_config import HydraConfig

    from unicorn.io.run_folder import in_sweep

    if not isinstance(err, Interrupted) or not in_sweep() or NoteExistingFolders.sweep is not None:
        return err
    sweep = Path(HydraConfig.get().sweep.dir).resolve()
    return Interrupted(
        f"{err}; the sweep goes on with the same command and hydra.sweep.dir={sweep} ckpt_path=last",
        err.exit_status,
    )


def _log_end(err: Exception) -> None:
    """Write how a run that trained ended into its log files (``train.log``), as the console gets it from the
    application: a signal's message, an expected failure's one line, a bug's traceback."""
    from unicorn.cli.errors import expected_error, one_line

    reported = None if isinstance(err, Interrupted) else expected_error(err)
    if isinstance(err, Interrupted):
        level, text, exc_info = logging.WARNING, one_line(err), None
    elif reported is not None:
        level, text, exc_info = logging.ERROR, f"error: {one_line(reported)}", None
    else:
        level, text, exc_info = logging.ERROR, f"failed: {type(err).__name__}", (type(err), err, err.__traceback__)
    record = log.makeRecord(log.name, level, __file__, 0, text, None, exc_info)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):  # the console has its own report (HydraApp)
            handler.handle(record)


def experiment_overrides(overrides: list[str]) -> list[str]:
    """``overrides`` (command-line arguments or compose overrides) with ``+experiment=V`` (and ``++experiment=V``)
    written ``experiment=V``.

    ``conf/train.yaml`` ends its defaults list with ``experiment: null``: a placeholder after ``_self_``, so that the
    chosen experiment is merged last and overrides everything above it, and one that the compose API
    (``compose("train", overrides=["experiment=cub"])``) fills like any group. Hydra fills such an entry with
    ``experiment=NAME``; ``+experiment=NAME``, the form of Hydra's "Configuring Experiments" page (whose primary
    config has no entry), asks to append a second one, which Hydra refuses ("Multiple values for experiment").
    Rewriting the ``+`` form is the one change that makes both forms compose the same run, in single runs, sweeps
    (``-m +experiment=a,b``; the sweep value is kept as written) and with ``-cd DIR``, whose ``DIR/experiment/``
    presets join the same group. A ``train.yaml`` of your own in ``DIR`` replaces ours and must keep the
    ``train_schema`` and ``experiment: null`` entries. Every other argument is returned unchanged.
    """
    # ++experiment=NAME (Hydra's add-or-override) too: Hydra refuses it for a config group
    return [arg.lstrip("+") if arg.startswith(("+experiment=", "++experiment=")) else arg for arg in overrides]


def open_node_overrides(overrides: list[str]) -> list[str]:
    """``overrides`` with ``key=value`` written ``++key=value`` where ``key`` is a node that the composed config may
    lack in part (:func:`unicorn.config.schema.open_nodes`) or one of its keys (a free mapping's at any depth):
    ``callbacks.heldout.split=test`` or ``callbacks.heldout={every_n_steps: 100, split: test}`` where the preset's
    ``callbacks.heldout`` names no ``split``, ``callbacks.extra.mine={...}``, ``dataset.synthetic.roll=0``,
    ``renderer.camera.focal_length=2`` where the preset's camera names a ``fov``. Hydra refuses these without a ``+``;
    with ``++`` (add, or merge into what is there) they work whether the key is there or not, and
    :func:`unicorn.config.validate` refuses the misspelt ones. Every other argument is returned unchanged."""
    from unicorn.config.schema import open_nodes

    nodes = open_nodes()
    rewritten = []
    for arg in overrides:
        key, equals, _ = arg.partition("=")
        node, _, name = key.rpartition(".")
        keys = nodes.get(node, ())
        known = key in nodes or (node in nodes and (keys is None or name in keys))  # the node, or one of its keys
        # or a key deeper in a free mapping, which takes any key at any depth (renderer.camera.focal_length)
        parts = key.split(".")
        known = known or any(nodes.get(".".join(parts[:i]), ()) is None for i in range(1, len(parts) - 1))
        # a key without a dot names a config group (renderer=hard, logger=none): a choice, never rewritten
        if equals and known and "." in key and not arg.startswith(("+", "~", "-")):
            arg = f"++{arg}"
        rewritten.append(arg)
    return rewritten


def hydra_argv(argv: list[str]) -> list[str]:
    """The arguments handed to Hydra: :func:`experiment_overrides` and :func:`open_node_overrides` of ``argv``, or
    ``experiment=synthetic`` (the offline default) when there are none."""
    return open_node_overrides(experiment_overrides(argv)) if argv else [f"experiment={DEFAULT_EXPERIMENT}"]


def argument_note(args: list[str]) -> str | None:
    """The line ``unicorn-train`` prints first when the arguments choose no experiment: none at all run the offline
    default; overrides without ``+experiment=NAME`` compose the generic config (``conf/train.yaml``), not that
    default. None when an experiment is chosen or for ``--help``."""
    if any(arg in ("--help", "-h", "--hydra-help") for arg in args):
        return None
    if not args:
        return (
            f"unicorn-train: no arguments, running the offline default +experiment={DEFAULT_EXPERIMENT} "
            "(see unicorn-train --help)"
        )
    if any(arg.lstrip("+").startswith("experiment=") for arg in args):
        return None
    return (
        "unicorn-train: no +experiment=NAME among the arguments: composing the generic config (conf/train.yaml; "
        f"unicorn-train --cfg job shows it), not the offline default +experiment={DEFAULT_EXPERIMENT}"
    )


def sweep_problem(args: list[str]) -> str | None:
    """What keeps a sweep (``-m``) over several experiments (task names, log folders) from being one sweep, or None:
    each job's folder is under its own value's (``outputs/<task_name>/multiruns/<time>/<job>``), so that the
    sweep's record and its jobs lie in different folders and no one ``hydra.sweep.dir`` resumes them all; it needs a
    folder of its own."""
    if not any(arg in ("-m", "--multirun") for arg in args):
        return None
    naming = swept_keys(args) & set(_FOLDER_NAMING)
    swept = [a for a in args if a.split("=", 1)[0].lstrip("+~") in naming]
    if not swept or any(a.lstrip("+").startswith("hydra.sweep.dir=") for a in args):
        return None
    return (
        f"{swept[0]}: a sweep over a setting that names the sweep's folder needs one folder for all its jobs, "
        "hydra.sweep.dir=DIR (by default each job goes under a folder of its own value, and no one folder resumes "
        "the sweep)"
    )


#: the settings the default sweep folder is named from (``${paths.log_dir}/${task_name}/multiruns/<time>``, the
#: experiment setting the task name)
_FOLDER_NAMING = ("experiment", "task_name", "paths.log_dir")


def main() -> None:
    """Console-script entry point (``unicorn-train``)."""
    global _app
    args = sys.argv[1:]
    debug = "--debug" in args
    args = [arg for arg in args if arg != "--debug"]
    if "--version" in args:
        from unicorn import __version__

        print(f"unicorn-train (unicorn3d) {__version__}")
        return
    problem = sweep_problem(args)
    if problem:
        print(f"unicorn-train: error: {problem}", file=sys.stderr)
        sys.exit(2)
    note = argument_note(args)
    if note:
        print(note, file=sys.stderr, flush=True)
    defer_stop_signals("unicorn-train")  # until the run can put its folders back (_task), a signal is noted, not fatal
    tune_allocator()
    tolerate_closed_stdout()  # ``unicorn-train ... | head``: training goes on, its records still reach train.log
    from unicorn.config.schema import store_schema  # imports torch: after --version and the allocator tuning

    store_schema()  # conf/train.yaml's defaults list starts with the schema
    _app = HydraApp("unicorn-train", config_dir(), "train", debug=debug)
    _app.run(_task, hydra_argv(args))


if __name__ == "__main__":
    main()
