"""A Hydra application whose errors are reported like every other command's (:mod:`unicorn.cli.errors`).

:class:`HydraApp` runs a task under ``hydra.main`` and handles every error once:

- before the task (Hydra's composition: a misspelt override or group, a run folder that cannot be created), what
  Hydra printed is held back and reported as ``<prog>: error: <one line>``, exit status 2, unless it is a bug;
- in the task, an expected failure (:func:`~unicorn.cli.errors.expected_error`) the same way, a bug with its
  traceback. In a sweep (``-m``) a job's expected failure is said with the job's number and swept values, a job's
  bug with them and its traceback, and the other jobs run; the command then ends with one line naming the failed
  jobs and status 2, or 1 when one of them failed with a bug (a :class:`~unicorn.cli.errors.SweepError`, a problem
  of the whole sweep, stops it at once).

Hydra writes its record of the run (``.hydra/``) before the task starts, over the record of a run whose folder
the task may then refuse; the app turns that off and the task writes the record once it accepted the folder
(:meth:`HydraApp.save_record`).

Hydra creates a job's folder before the task starts; :class:`NoteExistingFolders`, a Hydra callback the app adds,
notes beforehand which folders existed, so that the task can tell a folder it created (and may remove again)
from one the user made (:func:`entries_before`); a command stopped at once before its task took the folder over
(a second signal while it sets up) has what Hydra made for the job removed again. A sweep locks its folder and is
refused there, before Hydra writes into it, where another sweep runs, an earlier sweep's record would be replaced,
the folder holds a run, or the jobs would share one folder (:meth:`NoteExistingFolders.on_multirun_start`).

A task stopped by a signal (:class:`unicorn.errors.Interrupted`) prints its message as ``<prog>: <message>`` and
exits with the error's status. unicorn's warnings in the task are logged in one line, into the run's log too
(:func:`~unicorn.cli.errors.log_warnings`).
"""

from __future__ import annotations

import builtins
import io
import math
import os
import re
import shlex
import sys
import traceback
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import hydra
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from unicorn.cli.errors import SweepError, debug_requested, expected_error, log_warnings, one_line
from unicorn.errors import STOP_SIGNALS, Interrupted

__all__ = ["APP_OVERRIDES", "HydraApp", "NoteExistingFolders", "entries_before", "hydra_failure", "swept_keys"]


class NoteExistingFolders(Callback):
    """A Hydra callback noting, before Hydra creates any job folder or log, which of them exist already and what
    they hold: a single run's ``hydra.run.dir``; a sweep's ``hydra.sweep.dir`` and the folders in it (its job
    folders again after each job, :meth:`on_job_end`)."""

    #: the noted folder, whether its sub-folders are the jobs' (a sweep), and each existing folder's entries
    noted: tuple[Path, bool, dict[Path, set[str]]] | None = None
    #: why the command refuses the noted folder, or None: it cannot be created (it, or a folder above it, is a file;
    #: Hydra then fails), or it is a sweep's folder that a sweep may not use (:meth:`on_multirun_start` stops Hydra)
    refusal: str | None = None
    #: the outermost of the noted folder's missing ancestors (``outputs`` of ``outputs/train/runs/<time>`` in a
    #: new project), which Hydra creates with it; None when its parent exists
    created_top: Path | None = None
    #: a sweep's folder and what its record (:data:`unicorn.io.run_folder.SWEEP_RECORD`) held before Hydra
    #: rewrote it (None: no such file), kept while no job of the sweep has kept its folder (the task sets it to None
    #: once one has): a sweep none of whose jobs kept one puts them back (:meth:`put_back_sweep`)
    sweep: tuple[Path, bytes | None] | None = None
    #: the lock a sweep holds on its folder while it runs (:func:`unicorn.io.run_folder.lock_folder`), or None
    sweep_lock: Any = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        NoteExistingFolders.sweep = None
        self._note(Path(str(config.hydra.run.dir)), jobs_inside=False)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Note the sweep's folder, then refuse it before Hydra writes into it (its record, :data:`SWEEP_RECORD`,
        replaces the folder's) where the jobs would share one folder (``hydra.sweep.subdir``), where it holds a run
        or an earlier sweep that this one neither goes on with nor replaces
        (:func:`~unicorn.io.run_folder.plan_sweep_folder`), or where another sweep runs in it (its lock): the
        command stops with that one line, status 2 (:meth:`HydraApp.run`)."""
        from unicorn.io.run_folder import (
            SWEEP_RECORD,
            RunFolderBusyError,
            RunFolderError,
            lock_folder,
            plan_sweep_folder,
        )

        folder = Path(str(config.hydra.sweep.dir)).expanduser().resolve()
        NoteExistingFolders.sweep = None
        self._note(folder, jobs_inside=True)
        if NoteExistingFolders.refusal is not None:  # a folder Hydra cannot make: it fails, the app says why
            return
        shared = _shared_job_folder(config, folder)
        if shared is not None:  # before the lock and Hydra's record: nothing is written
            NoteExistingFolders.refusal = shared
            raise SystemExit(2) from None
        swept = swept_keys([str(o) for o in config.hydra.overrides.task])
        try:
            # locked first: a sweep started meanwhile is refused, or writes its record before this one reads it
            NoteExistingFolders.sweep_lock = lock_folder(folder, setting="hydra.sweep.dir")
            ckpt_arg = OmegaConf.select(config, "ckpt_path", throw_on_resolution_failure=False)
            overwrite = OmegaConf.select(config, "overwrite", default=False, throw_on_resolution_failure=False)
            # swept: each job's folder is checked with its own values
            plan_sweep_folder(folder, ckpt_arg, overwrite is True, jobs_decide=bool(swept & {"ckpt_path", "overwrite"}))
        except (RunFolderError, RunFolderBusyError) as err:
            NoteExistingFolders.refusal = one_line(err)
            # Hydra turns a callback's Exception into a warning and goes on: SystemExit stops it
            raise SystemExit(2) from None
        except OSError:  # the folder cannot be made or written (a read-only disk): Hydra fails there, the app says why
            pass
        record = folder / SWEEP_RECORD
        NoteExistingFolders.sweep = (folder, record.read_bytes() if record.is_file() else None)

    @staticmethod
    def release_sweep() -> None:
        """Give up the lock of the sweep's folder (nothing outside a sweep, or once given up)."""
        if NoteExistingFolders.sweep_lock is not None:
            NoteExistingFolders.sweep_lock.release()
            NoteExistingFolders.sweep_lock = None

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        """Note again, after each job of a sweep, what its job folders hold: the next job's folder may be one an
        earlier job of it made and trained in (``hydra.sweep.subdir`` naming two jobs' folders alike, another
        command's sweep into the same folder), whose run a refused job must not take for its own and remove."""
        noted = NoteExistingFolders.noted
        if noted is None or not noted[1] or not noted[0].is_dir():
            return
        folder, _, entries = noted
        jobs = _entries(folder.iterdir())
        if folder in entries:  # the sweep's folder keeps what it held before the sweep: put_back_sweep reads it
            jobs[folder] = entries[folder]
        NoteExistingFolders.noted = (folder, True, jobs)

    @staticmethod
    def put_back_sweep() -> None:
        """Put a sweep's record back as it was when none of its jobs kept a folder (each failed or was stopped
        before its first iteration, and put its own folder back): ``multirun.yaml`` gets back its bytes, or is
        removed, and then the sweep's folder and the parents Hydra created for it if they are empty. Nothing is
        removed but that file, the sweep's lock and empty folders; nothing happens outside a sweep. The sweep's
        folder is let go in any case (:meth:`release_sweep`): the command ends."""
        NoteExistingFolders.release_sweep()
        if NoteExistingFolders.sweep is None:
            return
        from unicorn.io.run_folder import SWEEP_RECORD, remove_empty_folders

        folder, record = NoteExistingFolders.sweep
        NoteExistingFolders.sweep = None
        path = folder / SWEEP_RECORD
        if record is None:
            path.unlink(missing_ok=True)
        elif not path.is_file() or path.read_bytes() != record:
            path.write_bytes(record)
        if entries_before(folder) is None:  # the sweep made it
            remove_empty_folders(folder, NoteExistingFolders.created_top or folder)

    @staticmethod
    def put_back_job() -> None:
        """Remove what the job under way left of its set-up when the command stopped at once before the task took
        its folder over (a second signal while it sets up: :func:`unicorn.errors.defer_stop_signals`): the empty log
        Hydra opened in it, the lock this process took, and the folder where Hydra created it and it is empty
        again (:func:`~unicorn.io.run_folder.put_back_set_up`). A folder that holds anything more, a run's or the
        user's, stays as it is."""
        from unicorn.io.run_folder import put_back_set_up

        noted = NoteExistingFolders.noted
        if noted is None:
            return
        folder, jobs_inside, entries = noted
        if not jobs_inside:
            put_back_set_up(folder, entries.get(folder), NoteExistingFolders.created_top)
            return
        # a sweep: the job under way's folder is one of its folders, noted before it began if it existed
        for job in sorted(folder.iterdir()) if folder.is_dir() else []:
            if job.is_dir() and not job.is_symlink():
                put_back_set_up(job, entries.get(job.resolve()))

    @staticmethod
    def _note(folder: Path, jobs_inside: bool) -> None:
        folder = folder.expanduser().resolve()
        NoteExistingFolders.refusal = None
        key = "hydra.sweep.dir" if jobs_inside else "hydra.run.dir"
        for path in (folder, *folder.parents):  # Hydra stops at it with "[Errno 17] File exists" (or 20)
            if path.exists() and not path.is_dir():
                where = "is a file" if path == folder else f"is inside {path}, which is a file"
                # said by the app when Hydra fails to create it (Hydra turns a callback's error into a warning)
                NoteExistingFolders.refusal = f"the run folder {folder} {where}: choose another folder ({key}=...)"
                return
        folders = [folder, *(folder.iterdir() if jobs_inside and folder.is_dir() else [])]
        NoteExistingFolders.noted = (folder, jobs_inside, _entries(folders))
        top = None
        while not folder.parent.exists() and folder.parent != folder:
            folder = top = folder.parent
        NoteExistingFolders.created_top = top


def _shared_job_folder(config: DictConfig, folder: Path) -> str | None:
    """Why a sweep into ``folder`` is refused for its ``hydra.sweep.subdir``, or None: the jobs' folder would be the
    sweep's folder itself (``hydra.sweep.subdir=.``: its record and lock are the sweep's), or one folder named
    without any value of the job (no ``${...}``) shared by several jobs, each of which would replace the run of the
    one before (with ``overwrite=true``) or be refused."""
    subdir = OmegaConf.to_container(config.hydra.sweep, resolve=False).get("subdir")
    if not isinstance(subdir, str) or "${" in subdir:  # named from the job (${hydra.job.num}, the default)
        return None
    job_folder = (folder / subdir).resolve()
    apart = "give each job a folder of its own (hydra.sweep.subdir=${hydra.job.num}, the default)"
    if job_folder == folder:
        return (
            f"hydra.sweep.subdir={subdir}: the jobs would train in the sweep's folder {folder} itself, which holds "
            f"the sweep's record; {apart}, or train one run without -m (hydra.run.dir={folder})"
        )
    jobs = _job_count(config)
    if jobs is not None and jobs > 1:
        return (
            f"hydra.sweep.subdir={subdir}: the {jobs} jobs of the sweep would all train in one folder, {job_folder}, "
            f"which holds one run; {apart}"
        )
    return None


def _job_count(config: DictConfig) -> int | None:
    """How many jobs a sweep runs under Hydra's basic sweeper: the product of the number of values of each swept
    key (its command line's and ``hydra.sweeper.params``); None under another sweeper, or when Hydra cannot parse
    the overrides (it says why itself)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if not str(OmegaConf.select(config, "hydra.sweeper._target_", default="")).endswith(".BasicSweeper"):
        return None
    params = OmegaConf.select(config, "hydra.sweeper.params", default=None) or {}
    args = [f"{key}={value}" for key, value in params.items()] + [str(o) for o in config.hydra.overrides.task]
    values: dict[str, int] = {}  # by key: a key given twice takes its last value, as in Hydra
    try:
        for override in OverridesParser.create().parse_overrides(args):
            sweep = override.is_discrete_sweep()
            values[override.get_key_element()] = len(list(override.sweep_string_iterator())) if sweep else 1
    except Exception:  # e.g. glob(), which needs Hydra's config loader: the count is unknown
        return None
    return math.prod(values.values())


def _entries(folders: Iterable[Path]) -> dict[Path, set[str]]:
    """What each of ``folders`` that is a folder holds (the names in it), by its resolved path."""
    return {f.resolve(): {p.name for p in f.iterdir()} for f in folders if f.is_dir()}


#: what the app adds to the overrides: no ``.hydra/`` record written by Hydra, the :class:`NoteExistingFolders`
APP_OVERRIDES = (
    "hydra.output_subdir=null",
    f"++hydra.callbacks.existing_folders._target_={__name__}.NoteExistingFolders",  # ++: DDP processes repeat it
)


def entries_before(folder: Path) -> set[str] | None:
    """The names ``folder`` held before Hydra created this process's job folders and logs; None when it did not
    exist then. A folder Hydra does not make (or when nothing was noted): what it holds now, None if missing."""
    folder = folder.resolve()
    noted = NoteExistingFolders.noted
    if noted is not None and (folder == noted[0] or (noted[1] and folder.parent == noted[0])):
        return noted[2].get(folder)
    return {p.name for p in folder.iterdir()} if folder.is_dir() else None


#: the exit statuses of a command stopped by a signal (``128 + signal``): one stopped at once while it set up says
#: so itself (:func:`unicorn.errors.defer_stop_signals`)
_STOPPED = frozenset(128 + signum for signum in STOP_SIGNALS)

#: argparse's report of a bad command line, after its usage lines: ``<prog>: error: <what>``
_ARGPARSE_ERROR = re.compile(r"^\S+: error: ")
#: the last line of a Python traceback: the exception's (qualified) name and message
_EXCEPTION_LINE = re.compile(r"^(?:[\w.]+\.)?(\w+): (.+)$")


def hydra_failure(text: str, overrides: Sequence[str] = (), config_dir: Path | None = None) -> str | None:
    """The one line to print for what Hydra reported before the task ran, or None when it is a bug.

    Without a traceback it is a composition error (a misspelt override or group); with one, an expected failure
    only when the traceback ends in an ``OSError`` (e.g. the run folder cannot be created on a read-only disk), in
    logging's failure to open the run's log that an ``OSError`` caused, or in Hydra's refusal of a config group set
    to null (``model=null``): named from ``overrides`` (the command line Hydra got), with the group's options in
    ``config_dir``.
    """
    lines = [line.strip() for line in text.splitlines() if line.strip() and "HYDRA_FULL_ERROR" not in line]
    if not any(line.startswith("Traceback (most recent call last)") for line in lines):
        argparse_errors = [line.split(": error: ", 1)[1] for line in lines if _ARGPARSE_ERROR.match(line)]
        if argparse_errors:  # argparse's usage lines, then "<prog>: error: <what>": the what
            line = argparse_errors[-1]
            if line.startswith("unrecognized arguments"):
                line += " (the key=value overrides go together, after Hydra's options: --cfg job seed=1)"
            return line
        line = " ".join(lines) or "invalid command line"
        chosen = _MULTIPLE_VALUES.match(line)
        added = _added_group_line(chosen.group(1), overrides) if chosen else None
        if added is not None:
            return added
        if "Could not find 'hydra/launcher/" in line:  # e.g. hydra/launcher=submitit_slurm without the plugin
            line += " (Hydra's launchers but basic are plugins of their own: pip install hydra-submitit-launcher)"
        if "mismatched input '='" in line:  # e.g. ckpt_path=run/checkpoints/step=0000010.ckpt
            given = next((arg for arg in overrides if "=" in _unquoted_value(arg)), None)
            example = _quoted(given) if given else "'ckpt_path=\"run/checkpoints/step=0000010.ckpt\"'"
            line += f" (a value holding '=' must be quoted for Hydra: {example})"
        elif "LexerNoViableAltException" in line or re.search(r"mismatched input '[()\[\]{}#]'", line):
            # e.g. hydra.run.dir=runs/café: letters outside ASCII, brackets, '#'; Hydra's line repeats the override
            given = next((arg for arg in overrides if _unquoted_value(arg) and f" {arg} ^" in line), None)
            example = _quoted(given) if given else "'hydra.run.dir=\"runs/café (1)\"'"
            line += (
                f" (a value holding letters outside ASCII, spaces, brackets or '#' must be quoted for Hydra: {example})"
            )
        return line
    match = _EXCEPTION_LINE.match(lines[-1])
    if match and _is_os_error(match):
        return match.group(2)
    if match and match.group(1) == "ValueError" and match.group(2).startswith(_NULL_GROUP):
        return _null_group(overrides, config_dir)
    if match and match.group(2).startswith("Unable to configure handler"):  # the run's log, from an OSError
        causes = [m for m in map(_EXCEPTION_LINE.match, lines) if m and _is_os_error(m)]
        if causes:
            return f"cannot write the run's log: {causes[-1].group(2)}"
    return None


def _unquoted_value(arg: str) -> str:
    """The value of an override ``key=value`` that is not quoted as a whole; the empty string otherwise."""
    key, sep, value = arg.partition("=")
    quoted = len(value) > 1 and value[0] in "'\"" and value[-1] == value[0]
    return value if sep and key and not key.startswith("-") and not quoted else ""


def _quoted(arg: str) -> str:
    """An override ``key=value`` with its value quoted for Hydra, the whole quoted for a shell: 'key="value"'."""
    key, _, value = arg.partition("=")
    return shlex.quote(f'{key}="{value}"')


#: Hydra's error for a config group chosen twice, with a hint about the ``override`` keyword of config files
_MULTIPLE_VALUES = re.compile(r"^Multiple values for (\S+)\. ")


def _added_group_line(group: str, overrides: Sequence[str]) -> str | None:
    """The line for Hydra's "Multiple values for ``group``" when the command line appends the group (``+G=V``,
    ``+G@pkg=V``) that the config already chooses, or appends it twice; None when it does neither."""
    added = [arg for arg in overrides if arg.partition("=")[1] and arg.partition("=")[0] == f"+{group}"]
    if len(added) > 1:
        return f"{', '.join(added)}: {group} is chosen more than once; give it once"
    if added:
        return f"{added[0]}: the config already chooses a {group}; write {added[0][1:]} (without +)"
    return None


#: Hydra's error for a config group override whose value is null (``model=null``, ``+experiment=null``)
_NULL_GROUP = "Config group override must be a string or a list"


def _null_group(overrides: Sequence[str], config_dir: Path | None) -> str:
    """The line for a config group set to null: the override, and the group's options where ``config_dir`` has
    it."""
    for arg in overrides:
        key, sep, value = arg.partition("=")
        group = key.lstrip("+")
        if not sep or value.strip() != "null" or key.startswith("~") or "." in group:  # a group has no dots
            continue
        folder = config_dir / group if config_dir is not None else None
        options = sorted(p.stem for p in folder.glob("*.yaml")) if folder is not None and folder.is_dir() else []
        choose = f"one of its options ({', '.join(options)})" if options else "one of its options"
        return f"{arg}: a config group cannot be null; choose {choose}, or leave the override out"
    return "a config group override is null: choose one of the group's options, or leave the override out"


def _is_os_error(match: re.Match[str]) -> bool:
    """Whether an exception line of a traceback (:data:`_EXCEPTION_LINE`) names an ``OSError``."""
    cls = getattr(builtins, match.group(1), None)
    return isinstance(cls, type) and issubclass(cls, OSError)


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


#: Hydra's options that take a value in the next argument (``--info``'s value is optional and one of its topics)
_VALUE_OPTIONS = {
    "--cfg",
    "-c",
    "--package",
    "-p",
    "--config-path",
    "-cp",
    "--config-name",
    "-cn",
    "--config-dir",
    "-cd",
    "--experimental-rerun",
}
_INFO_TOPICS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}


#: the overrides naming a folder Hydra creates, where ``~`` means the home folder as in a shell
_FOLDER_KEYS = ("hydra.run.dir", "hydra.sweep.dir")


def _home_expanded(value: str) -> str:
    """An override's value with a leading ``~`` expanded (``"~/runs"`` quoted or not): Hydra would create a folder
    named ``~`` in the current one."""
    quote = value[0] if value[:1] in ("'", '"') and value[-1:] == value[:1] and len(value) > 1 else ""
    inner = value[1:-1] if quote else value
    return f"{quote}{os.path.expanduser(inner)}{quote}" if inner.startswith("~") else value


def _empty_folder(args: Sequence[str]) -> str | None:
    """The error for a folder override left empty (``hydra.run.dir=$RUN`` with ``RUN`` unset), which Hydra would
    take for the current folder, or None."""
    for arg in args:
        key, sep, value = arg.partition("=")
        if sep and key.lstrip("+") in _FOLDER_KEYS and not value.strip().strip("'\"").strip():
            name = key.lstrip("+")
            return f"{name} is empty: give the folder, or leave {name} out for a new folder under paths.log_dir"
    return None


def _sweep_job(swept: set[str]) -> str:
    """``#<number> (<its values of the swept keys>)`` for a job of a sweep (``-m``), the empty string otherwise."""
    from hydra.core.hydra_config import HydraConfig

    from unicorn.io.run_folder import in_sweep, sweep_job_overrides

    if not in_sweep():
        return ""
    values = [override for key, override in sweep_job_overrides() if key in swept]
    return f"#{HydraConfig.get().job.num}" + (f" ({' '.join(values)})" if values else "")


def swept_keys(args: list[str]) -> set[str]:
    """The keys a command line sweeps (``seed=0,1``, ``lr=choice(...)``; not a list value such as ``x=[1,2]``)."""
    keys = set()
    for arg in args:
        key, sep, value = arg.partition("=")
        if sep and not key.startswith("-") and _is_sweep_value(value):
            keys.add(key.lstrip("+~"))
    return keys


def _is_sweep_value(value: str) -> bool:
    """Whether an override's value is one of Hydra's sweeps: a comma outside brackets and quotes, or a sweep
    function (``choice``, ``range``, ``interval``, ``glob``)."""
    if re.match(r"^\s*(choice|range|interval|glob)\(", value):
        return True
    depth, quote = 0, ""
    for char in value:
        if quote:
            quote = "" if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char in "[{(":
            depth += 1
        elif char in "]})":
            depth -= 1
        elif char == "," and depth == 0:
            return True
    return False


def _is_override(args: list[str], i: int) -> bool:
    """Whether ``args[i]`` is one of Hydra's positional overrides (not an option nor an option's value)."""
    if args[i].startswith("-"):
        return False
    before = args[i - 1] if i else ""
    return before not in _VALUE_OPTIONS and not (before == "--info" and args[i] in _INFO_TOPICS)


class HydraApp:
    """``hydra.main`` for a command, with its errors reported once (see the module docstring).

    Args:
        prog: the command's name (``<prog>: error: ...``).
        config_dir: the primary config's folder.
        config_name: the primary config.
        debug: tracebacks for expected failures too (``--debug``).
    """

    def __init__(self, prog: str, config_dir: Path, config_name: str, debug: bool = False) -> None:
        self.prog, self.config_dir, self.config_name, self.debug = prog, config_dir, config_name, debug
        self.record_subdir: str | None = ".hydra"  # where the task writes Hydra's record (None: nowhere)
        self.task_started = False
        #: the jobs of a sweep that failed (``#<num> (<overrides>)``): the sweep goes on with the others and the
        #: command ends with status 2, or 1 after a bug
        self.failed_jobs: list[str] = []
        self.failed_with_bug = False  # one of them with a bug (not an expected error): status 1
        self.jobs_started = 0
        self.sweep_dir: Path | None = None
        self.swept: set[str] = set()  # the keys the command line sweeps

    def hydra_args(self, args: list[str]) -> list[str]:
        """The arguments with Hydra's own writing of ``.hydra/`` turned off; a ``hydra.output_subdir`` given by the
        user is kept for :meth:`save_record`."""
        rest = []
        for arg in args:
            key, _, value = arg.partition("=")
            if key.lstrip("+~") == "hydra.output_subdir":
                self.record_subdir = None if value in ("", "null") or key.startswith("~") else value
            elif key.lstrip("+") in _FOLDER_KEYS:
                rest.append(f"{key}={_home_expanded(value)}")
            else:
                rest.append(arg)
        # beside the user's overrides: argparse takes Hydra's overrides as one run of positional arguments; without
        # any, first (after the options, an option missing its value, such as --info's topic, would take them)
        at = next((i for i in range(len(rest)) if _is_override(rest, i)), 0)
        return [*rest[:at], *APP_OVERRIDES, *rest[at:]]

    def save_record(self, cfg: DictConfig, output_dir: Path) -> None:
        """Hydra's record of the run (``config.yaml``, ``hydra.yaml``, ``overrides.yaml`` in ``.hydra/``), as
        Hydra writes it, into a run folder the task accepted."""
        from hydra.core.hydra_config import HydraConfig

        if self.record_subdir is None or not HydraConfig.initialized():
            return
        # a plain copy (Hydra's is read-only), interpolations kept as Hydra saves them
        hydra_cfg = OmegaConf.create(OmegaConf.to_container(HydraConfig.instance().cfg, resolve=False))
        hydra_cfg.hydra.output_subdir = self.record_subdir
        folder = output_dir / self.record_subdir
        folder.mkdir(parents=True, exist_ok=True)
        for name, node in (("config", cfg), ("hydra", hydra_cfg), ("overrides", hydra_cfg.hydra.overrides.task)):
            OmegaConf.save(node, folder / f"{name}.yaml")

    def _run_task(self, task: Callable[[DictConfig], Any], cfg: DictConfig) -> None:
        self.task_started = True
        self.jobs_started += 1
        if NoteExistingFolders.noted is not None and NoteExistingFolders.noted[1]:  # a sweep: its folder
            self.sweep_dir = NoteExistingFolders.noted[0]
        if isinstance(sys.stderr, _HeldStream):
            sys.stderr = sys.stderr.release()
        try:
            with log_warnings():  # into the run's train.log too
                task(cfg)
        except Interrupted as err:
            print(f"{self.prog}: {one_line(err)}", file=sys.stderr, flush=True)
            raise SystemExit(err.exit_status) from None
        except Exception as err:
            reported = expected_error(err)
            job = "" if isinstance(reported, SweepError) else _sweep_job(self.swept)
            if debug_requested(self.debug) or (reported is None and not job):
                raise  # a bug: Hydra prints the traceback, exit status 1
            if reported is None:  # a bug in a job of a sweep: Hydra would print only the first one's, after the sweep
                print(f"{self.prog}: error: job {job}: a bug, its traceback:", file=sys.stderr, flush=True)
                traceback.print_exception(err, file=sys.stderr)
                self.failed_with_bug = True
            else:
                print(f"{self.prog}: error: {job and f'job {job}: '}{one_line(reported)}", file=sys.stderr, flush=True)
            if not job:
                raise SystemExit(2) from None
            self.failed_jobs.append(job)  # the other jobs of the sweep still run

    def _end_sweep(self) -> None:
        """After a sweep some of whose jobs failed: one line naming them, exit status 2 (1 when one failed with a
        bug). Where the sweep's folder is gone (no job kept one, :meth:`NoteExistingFolders.put_back_sweep`), the
        line says that the same command runs the sweep again, not how to resume that folder."""
        if not self.failed_jobs:
            return
        status = 1 if self.failed_with_bug else 2
        where = f" hydra.sweep.dir={self.sweep_dir}" if self.sweep_dir is not None else ""
        then = f"the same command with{where} ckpt_path=last goes on with the sweep once the failures are fixed"
        if self.sweep_dir is not None and not self.sweep_dir.is_dir():
            then = "nothing of the sweep was kept: the same command runs it again once the failures are fixed"
        failed = len(self.failed_jobs)
        which = (
            f"every job of the sweep failed ({failed}), each said above: {', '.join(self.failed_jobs)}"
            if failed == self.jobs_started
            else f"{failed} job(s) of the sweep failed, each said above: {', '.join(self.failed_jobs)}; the other "
            "jobs ran"
        )
        print(f"{self.prog}: error: {which} ({then})", file=sys.stderr, flush=True)
        raise SystemExit(status)

    def run(self, task: Callable[[DictConfig], Any], args: list[str]) -> None:
        """Run ``task`` on the config Hydra composes from ``args`` (the command line after the program name)."""
        empty = _empty_folder(args)
        if empty is not None:
            print(f"{self.prog}: error: {empty}", file=sys.stderr)
            raise SystemExit(2)
        sys.argv[1:] = self.hydra_args(args)
        self.swept = swept_keys(args)
        held = None if debug_requested(self.debug) else _HeldStream(sys.stderr)
        if held is not None:
            sys.stderr = held
        main = hydra.main(config_path=str(self.config_dir), config_name=self.config_name, version_base="1.3")
        try:
            main(lambda cfg: self._run_task(task, cfg))()
            NoteExistingFolders.put_back_sweep()  # when every job failed before training
            self._end_sweep()
        except SystemExit as exit:
            NoteExistingFolders.put_back_job()  # before the sweep's folder, which it may leave empty
            NoteExistingFolders.put_back_sweep()
            if self.task_started or not exit.code or exit.code in _STOPPED:  # a signal: its line is said (held)
                raise
            if held is None and NoteExistingFolders.refusal is None:  # --debug: Hydra printed its traceback
                raise
            if held is not None:
                sys.stderr = held.stream
            # Hydra's own report of an error before the task: one line, status 2, unless it is a bug
            line = NoteExistingFolders.refusal or hydra_failure(held.held.getvalue(), args, self.config_dir)
            if line is None:
                sys.stderr.write(held.held.getvalue())
                raise
            print(f"{self.prog}: error: {line}", file=sys.stderr)
            raise SystemExit(2) from None
        except ValueError as err:  # Hydra's check of its modes, raised before it reads anything else
            if self.task_started or not str(err).startswith("Only one of --run, --multirun, --cfg"):
                raise
            if held is not None:
                sys.stderr = held.stream
            hint = (
                "Hydra runs one of these at a time: --cfg job prints one run's config, without -m and one value per key"
            )
            print(f"{self.prog}: error: {err} ({hint})", file=sys.stderr)
            raise SystemExit(2) from None
        finally:
            NoteExistingFolders.release_sweep()
            if isinstance(sys.stderr, _HeldStream):
                sys.stderr = sys.stderr.release()
