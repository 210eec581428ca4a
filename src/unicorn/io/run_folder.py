"""A training run's folder: what a run writes there, resuming from it, refusing to overwrite an earlier run, the
lock that keeps a second run out, and undoing what a run that fails before its first iteration wrote.

A folder that already holds a run is only trained in again to resume it (``ckpt_path``) or with
``overwrite=true`` (its outputs are deleted first); ``unicorn-train`` (:mod:`unicorn.cli.train`) applies these rules:

- :func:`plan_folder` checks a folder before anything is built and returns what the run will delete; nothing is
  written or deleted until the whole run is built (:func:`clear`);
- :func:`plan_sweep_folder` checks a sweep's folder (``-m``) before Hydra writes its record there;
- :func:`lock_folder` holds the folder for one process at a time;
- :class:`FolderChanges` undoes what a run wrote into a folder when it fails before its first iteration: it removes
  a folder the run created, or in an existing folder only what the run added, and restores the records it
  rewrote.
"""

from __future__ import annotations

import contextlib
import fcntl
import fnmatch
import logging
import os
import re
import secrets
import shlex
import shutil
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from unicorn.errors import UserError
from unicorn.io.serialization import CheckpointNotFoundError, check_checkpoint_path
from unicorn.torch_files import torch_file_problem

__all__ = [
    "resume_hint",
    "LOCK_NAME",
    "RUN_LOG",
    "RUN_FOLDER_FILES",
    "RUN_OUTPUTS",
    "RUN_PROVENANCE",
    "RUN_RECORDS",
    "RUN_TABLES",
    "STEP_CHECKPOINT",
    "SWEEP_RECORD",
    "FolderChanges",
    "FolderLock",
    "RunFolderBusyError",
    "ASIDE_PREFIX",
    "RunFolderError",
    "checkpoint_step",
    "drop_aside",
    "folder_setting",
    "in_sweep",
    "put_back_aside",
    "remove_empty_folders",
    "set_aside",
    "later_checkpoints",
    "lock_folder",
    "newest_checkpoint",
    "plan_folder",
    "plan_sweep_folder",
    "put_back_set_up",
    "previous_run",
    "resolve_ckpt",
    "run_config",
    "run_dataset",
    "run_of_checkpoint",
    "step_checkpoints",
    "sweep_job_overrides",
]

log = logging.getLogger("unicorn.train")

#: the tables a run writes at the top of its folder (each rewritten whole at every row)
RUN_TABLES = ("heldout.csv", "diagnostics.csv")
#: what a run writes into its folder as its outputs (replaced by ``overwrite=true``)
RUN_OUTPUTS = ("checkpoints", "csv", "tensorboard", "images", "eval", *RUN_TABLES)
#: the entries a run writes in each of its output folders (glob patterns; hidden names are temporary files):
#: ``overwrite=true`` refuses to delete a folder holding anything else
RUN_FOLDER_FILES = {
    "checkpoints": ("last.ckpt", "step=*.ckpt", "nonfinite-step=*.ckpt", ".*"),
    "csv": ("metrics.csv", "hparams.yaml", ".*", "metrics.csv.tmp-*"),  # the last: a killed rewrite of unicorn 0.1.0
    "tensorboard": ("events.out.tfevents.*", "hparams.yaml", ".*"),
    "images": ("step=*.png", ".*"),
    "eval": ("metrics.csv", "metrics.json", "per_image.csv", "report.html", "report.png", "report", "_viewer", ".*"),
}
#: the hidden folder of a run folder (``.overwritten-<pid>-<token>``) holding the earlier run's outputs that
#: ``overwrite=true`` replaces, from the moment the new run writes until its first iteration is done
ASIDE_PREFIX = ".overwritten-"
_ASIDE_TOKEN = secrets.token_hex(4)
#: the record of a run's starts, which only ``unicorn-train`` writes: what tells its records from a user's own files
RUN_PROVENANCE = "provenance.json"
#: the records of the run a folder holds (its config, its starts, Hydra's record): a resumed run rewrites them
RUN_RECORDS = ("config.yaml", RUN_PROVENANCE, ".hydra")
#: the log Hydra appends to (``<hydra.job.name>.log``)
RUN_LOG = "train.log"
#: everything a run writes at the top of its folder: its outputs, records and logs (the log of each further DDP
#: process is named by Lightning, which launches it with ``hydra.job.name=train_ddp_process_<rank>``)
_RUN_ENTRIES = (*RUN_OUTPUTS, *RUN_RECORDS, RUN_LOG, "train_ddp_process_*.log")
#: the record of a sweep (``-m``) Hydra writes into ``hydra.sweep.dir``, whose jobs' runs are in its numbered folders
SWEEP_RECORD = "multirun.yaml"
#: the lock file of a folder a run is training in (:func:`lock_folder`)
LOCK_NAME = ".unicorn-train.lock"
#: the periodic checkpoints' names (``step=<N>.ckpt``; ``-v<k>`` for Lightning's copies of a name in use)
STEP_CHECKPOINT = re.compile(r"step=(\d+)(-v\d+)?\.ckpt")


def in_sweep() -> bool:
    """Whether this process runs a job of a Hydra sweep (``-m``)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def resume_hint(run_dir: str | Path) -> str:
    """What to add to a stopped run's command to resume it in its folder ``run_dir``: the overrides that name the
    folder, where a Hydra command ran one run (so that a folder Hydra timestamped is named too);
    ``ckpt_path=last in the same folder`` for a job of a sweep (whose own hint names the sweep's folder) or a run
    built from Python."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized() and not in_sweep():
        return f"hydra.run.dir={shlex.quote(str(run_dir))} ckpt_path=last"
    return "ckpt_path=last in the same folder"


def sweep_job_overrides() -> list[tuple[str, str]]:
    """This job of a sweep's (``-m``) command-line overrides as ``(key, override)``: ``("seed", "seed=1")``, the key
    without Hydra's ``+`` / ``~`` prefixes; none outside a sweep."""
    if not in_sweep():
        return []
    from hydra.core.hydra_config import HydraConfig

    return [(o.split("=", 1)[0].lstrip("+~"), o) for o in HydraConfig.get().overrides.task]


def folder_setting() -> str:
    """The setting that names a run's folder, as the refusals tell the user to change it: ``hydra.sweep.dir`` in a
    job of a sweep (``-m``; Hydra ignores ``hydra.run.dir`` there), else ``hydra.run.dir``."""
    return "hydra.sweep.dir" if in_sweep() else "hydra.run.dir"


class RunFolderError(UserError, FileExistsError):
    """A new run was started in a folder that already holds one, or a resume would delete later checkpoints."""


class RunFolderBusyError(UserError, BlockingIOError):
    """Another process is training in the run folder."""


def step_checkpoints(checkpoint_dir: Path) -> list[tuple[int, Path]]:
    """The periodic checkpoints (``step=<N>.ckpt``) in ``checkpoint_dir`` as ``(N, path)``, oldest first."""
    if not checkpoint_dir.is_dir():
        return []
    found = []
    for path in checkpoint_dir.iterdir():
        match = STEP_CHECKPOINT.fullmatch(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return sorted(found)


def newest_checkpoint(checkpoint_dir: Path) -> Path | None:
    """The checkpoint of ``checkpoint_dir`` saved at the latest iteration: ``last.ckpt`` or a ``step=<N>.ckpt``
    (``last.ckpt`` on a tie; one whose iteration cannot be read counts as iteration 0), None when there is none."""
    found = step_checkpoints(checkpoint_dir)
    last = checkpoint_dir / "last.ckpt"
    if last.is_file() and (not found or (checkpoint_step(last) or 0) >= found[-1][0]):
        return last
    return found[-1][1] if found else None


def checkpoint_step(path: Path) -> int | None:
    """The iteration a checkpoint was saved at (``step=<N>.ckpt`` by its name, any other file by its stored
    ``global_step``, read without loading its tensors), or None when it cannot be read safely."""
    match = STEP_CHECKPOINT.fullmatch(path.name)
    if match:
        return int(match.group(1))
    import torch

    if torch_file_problem(path):  # e.g. a zip whose compressed entries would inflate in memory
        return None
    try:
        data = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # unreadable without trust, or not a checkpoint: the step is unknown
        return None
    step = data.get("global_step") if isinstance(data, Mapping) else None
    return step if isinstance(step, int) else None


def resolve_ckpt(ckpt_path: str | None, checkpoint_dir: Path, save_last: bool = True) -> str | None:
    """The checkpoint to resume from: None for ``None``; for ``"last"`` this run folder's ``last.ckpt``, or, for a
    run that writes it only when a signal stops it (``save_last=False``, ``callbacks.checkpoint.save_last``), the
    newest of it and the ``step=<N>.ckpt`` files; None when there is none (training starts from scratch);
    otherwise the existing file ``ckpt_path`` names.

    A run that writes ``last.ckpt`` but has none was killed before its first one was complete: it starts again,
    and its periodic checkpoints of that attempt are written again (:class:`~unicorn.lit.PeriodicCheckpoint`),
    so that its metric logs, which lag its checkpoints by an iteration, hold every iteration once.

    Raises:
        unicorn.io.serialization.CheckpointNotFoundError: ``ckpt_path`` names no file.
    """
    if ckpt_path is None:
        return None
    if not str(ckpt_path).strip():
        raise CheckpointNotFoundError("ckpt_path is empty: name a checkpoint file, or last to resume this folder's run")
    if ckpt_path == "last":
        last = checkpoint_dir / "last.ckpt"
        if save_last and last.is_file():
            return str(last)
        newest = None if save_last else newest_checkpoint(checkpoint_dir)  # last.ckpt: written by a signal
        if newest is not None:
            log.info("ckpt_path=last: resuming from the newest checkpoint %s (save_last=false)", newest)
            return str(newest)
        if not checkpoint_dir.is_dir() and (checkpoint_dir.parent / RUN_PROVENANCE).is_file():
            folder = checkpoint_dir.parent
            log.info("ckpt_path=last: %s holds a run killed before its first checkpoint: training it again", folder)
        elif not checkpoint_dir.is_dir() and in_sweep() and _holds_a_run_beside(checkpoint_dir.parent):
            # a resumed sweep's job that the sweep had not reached: its sweep folder was named, as the warning says
            log.info(
                "ckpt_path=last: %s holds no run yet (a job the sweep had not reached): training it from scratch",
                checkpoint_dir.parent,
            )
        elif not checkpoint_dir.is_dir():  # a folder without a run: most likely not the run's folder
            setting = folder_setting()
            log.warning(
                "ckpt_path=last: %s holds no run to resume, training from scratch (to resume a run, name its folder: "
                "%s=<%s>)",
                checkpoint_dir.parent,
                setting,
                "sweep dir" if setting == "hydra.sweep.dir" else "run dir",
            )
        else:
            log.info("ckpt_path=last: no %s yet, training from scratch", last)
        return None
    return str(check_checkpoint_path(Path(ckpt_path).expanduser().resolve(), "ckpt_path"))


def _holds_a_run_beside(folder: Path) -> bool:
    """Whether a folder beside ``folder`` (another job's of its sweep) holds a run (:data:`RUN_PROVENANCE`)."""
    try:
        return any((f / RUN_PROVENANCE).is_file() for f in folder.parent.iterdir() if f != folder and f.is_dir())
    except OSError:  # the sweep's folder unreadable: said where it is used
        return False


def later_checkpoints(checkpoint_dir: Path, ckpt: Path) -> list[Path]:
    """The checkpoints in ``checkpoint_dir`` saved after the iteration of ``ckpt``: what a run resumed from
    ``ckpt`` deletes (``step=<N>.ckpt``) or replaces (``last.ckpt``). A ``last.ckpt`` whose iteration cannot be
    read counts as later."""
    step = checkpoint_step(ckpt)
    if step is None:
        return []  # Lightning reports an unreadable checkpoint when it loads it
    later = [path for n, path in step_checkpoints(checkpoint_dir) if n > step and path != ckpt]
    last = checkpoint_dir / "last.ckpt"
    if last.is_file() and last != ckpt:
        last_step = checkpoint_step(last)
        if last_step is None or last_step > step:
            later.append(last)
    return later


def previous_run(output_dir: Path) -> Path | None:
    """The first output of an earlier run found in ``output_dir`` (a checkpoint, a metric log...), or None."""
    checkpoints = output_dir / "checkpoints"
    if checkpoints.is_dir():
        found = next((p for p in sorted(checkpoints.iterdir()) if p.suffix == ".ckpt"), None)
        if found is not None:
            return found
    for name in RUN_OUTPUTS[1:]:
        path = output_dir / name
        if path.is_file() or (path.is_dir() and any(path.iterdir())):
            return path
    return None


def plan_folder(output_dir: Path, ckpt_arg: str | None, ckpt: str | None, overwrite: bool) -> list[Path]:
    """Check that a run may train in ``output_dir``; returns what it deletes first (:func:`clear`). Reads only.

    Args:
        output_dir: the run folder.
        ckpt_arg: the ``ckpt_path`` setting (None: a new run; ``"last"``: continue the run this folder holds).
        ckpt: the checkpoint it resolved to (:func:`resolve_ckpt`).
        overwrite: the ``overwrite`` setting.

    Raises:
        RunFolderError: a sweep's folder (:data:`SWEEP_RECORD`); a new run, or a run resumed from another folder's
            checkpoint, in a folder holding a run, or holding the records of one (``config.yaml``...); a resume from
            a checkpoint older than checkpoints of this folder; each unless ``overwrite``. With ``overwrite``,
            outputs to replace that hold files a run does not write, or that are links.
    """
    rel = lambda p: p.relative_to(output_dir) if p.is_relative_to(output_dir) else p  # noqa: E731
    for aside in sorted(output_dir.glob(f"{ASIDE_PREFIX}*")) if output_dir.is_dir() else []:
        log.warning(
            "%s holds the outputs of a run that overwrite=true replaced, set aside by a run killed before its first "
            "iteration: move them back into %s, or delete the folder",
            aside,
            output_dir,
        )
    if (output_dir / SWEEP_RECORD).is_file():
        raise RunFolderError(
            f"{output_dir} is a sweep's folder ({SWEEP_RECORD}): its jobs' runs are in its numbered folders; resume "
            f"one with hydra.run.dir={output_dir}/<job number>, the whole sweep with -m and hydra.sweep.dir, or "
            f"train elsewhere ({folder_setting()}=...)"
        )
    previous = previous_run(output_dir)
    if ckpt_arg == "last" and overwrite and previous is not None:  # the run is resumed: nothing is replaced
        log.warning(
            "overwrite=true is not used: ckpt_path=last resumes the run %s holds (drop ckpt_path to replace it)",
            output_dir,
        )
    elsewhere = ckpt_arg not in (None, "last") and ckpt is not None and not _in_folder(Path(ckpt), output_dir)
    if (ckpt_arg is None or elsewhere) and previous is not None:
        if not overwrite:
            started = (
                "" if ckpt_arg is None else f"; {ckpt} is another run's checkpoint (continue that run in its folder)"
            )
            raise RunFolderError(
                f"{output_dir} already holds a run ({rel(previous)}){started}; resume it with ckpt_path=last, replace "
                f"it with overwrite=true, or train elsewhere ({folder_setting()}=...)"
            )
        outputs = [output_dir / name for name in RUN_OUTPUTS if (output_dir / name).exists()]
        _check_replaceable(outputs, output_dir)
        return outputs
    records = [name for name in RUN_RECORDS if (output_dir / name).exists()]
    if records and previous is None and not overwrite:
        killed = (output_dir / RUN_PROVENANCE).is_file()  # a config.yaml without it may be the user's own
        if ckpt_arg != "last" or not killed:
            hint = (
                " (a run killed before its first checkpoint: ckpt_path=last trains it again from the start in this "
                "folder)"
                if killed
                else ""
            )
            raise RunFolderError(
                f"{output_dir} holds {', '.join(records)} but no run; train elsewhere ({folder_setting()}=...), remove "
                f"them, or replace them with overwrite=true{hint}"
            )
    if ckpt_arg not in (None, "last") and ckpt is not None:
        later = later_checkpoints(output_dir / RUN_OUTPUTS[0], Path(ckpt))
        if later and not overwrite:
            names = ", ".join(str(rel(p)) for p in later)
            raise RunFolderError(
                f"resuming from {rel(Path(ckpt))} would delete or replace the later checkpoints {names}; pass "
                f"overwrite=true to go on, or train elsewhere ({folder_setting()}=...)"
            )
    return []


def plan_sweep_folder(folder: Path, ckpt_arg: str | None, overwrite: bool, jobs_decide: bool = False) -> None:
    """Check that a sweep (``-m``) may run in ``folder`` (``hydra.sweep.dir``) before Hydra writes its record there
    (:data:`SWEEP_RECORD`, which replaces the one the folder holds); reads only. As for a run's folder
    (:func:`plan_folder`), a folder holding an earlier sweep is only used again to go on with that sweep or to
    replace it; a folder holding a run is never a sweep's (the record would keep the run from being resumed there).

    Args:
        folder: the sweep's folder.
        ckpt_arg: the ``ckpt_path`` setting of the sweep (``"last"``: go on with the sweep the folder holds).
        overwrite: the ``overwrite`` setting of the sweep.
        jobs_decide: ``ckpt_path`` or ``overwrite`` is swept: each job checks its folder with its own values, and
            an earlier sweep's record is not refused here.

    Raises:
        RunFolderError: ``folder`` holds a run; or it holds :data:`SWEEP_RECORD`, and the sweep neither goes on with
            it (``ckpt_path=last``) nor replaces it (``overwrite=true``).
    """
    run = folder / RUN_PROVENANCE if (folder / RUN_PROVENANCE).is_file() else previous_run(folder)
    if run is not None:
        raise RunFolderError(
            f"{folder} holds a run ({run.relative_to(folder)}), not a sweep: a sweep's folder holds its jobs' folders, "
            "and its record there would keep the run from being resumed; sweep elsewhere (hydra.sweep.dir=...)"
        )
    if (folder / SWEEP_RECORD).is_file() and ckpt_arg != "last" and not overwrite and not jobs_decide:
        raise RunFolderError(
            f"{folder} holds an earlier sweep ({SWEEP_RECORD}, Hydra's record of it); go on with it with "
            "ckpt_path=last, replace its runs with overwrite=true, or sweep elsewhere (hydra.sweep.dir=...)"
        )


def _in_folder(ckpt: Path, output_dir: Path) -> bool:
    """Whether ``ckpt`` is one of ``output_dir``'s own checkpoints (in its ``checkpoints/``, through any links)."""
    return os.path.realpath(ckpt.parent) == os.path.realpath(output_dir / RUN_OUTPUTS[0])


def _check_replaceable(outputs: list[Path], output_dir: Path) -> None:
    """Refuse to replace outputs that hold what a run does not write (:data:`RUN_FOLDER_FILES`), or that are links
    (the run would write through them into the folder they lead to).

    Raises:
        RunFolderError: names the first few such entries.
    """
    for path in outputs:
        if path.is_symlink():
            raise RunFolderError(
                f"overwrite=true: {path} is a link to {os.path.realpath(path)}, which a run does not replace; remove "
                f"the link or train elsewhere ({folder_setting()}=...)"
            )
    foreign = [
        entry
        for path in outputs
        if path.is_dir() and path.name in RUN_FOLDER_FILES
        for entry in sorted(path.iterdir())
        if not _written_by_unicorn(entry, RUN_FOLDER_FILES[path.name])
    ]
    if foreign:
        names = ", ".join(str(p.relative_to(output_dir)) for p in foreign[:4])
        more = f" and {len(foreign) - 4} more" if len(foreign) > 4 else ""
        raise RunFolderError(
            f"overwrite=true would delete {names}{more}, which unicorn-train did not write: move them out of "
            f"{output_dir}'s run folders first"
        )


def _written_by_unicorn(entry: Path, patterns: tuple[str, ...]) -> bool:
    """Whether ``entry`` of a run's output folder is one a run writes (``patterns``), or, in ``eval/``, the folder
    ``unicorn-eval`` writes by default for a checkpoint of the run (``eval/<dataset>_<split>/``): its metrics and
    report, nothing else."""
    if any(fnmatch.fnmatchcase(entry.name, p) for p in patterns):
        return True
    evaluation = RUN_FOLDER_FILES["eval"]
    return (
        patterns == evaluation
        and entry.is_dir()
        and not entry.is_symlink()
        and (entry / "metrics.json").is_file()
        and all(any(fnmatch.fnmatchcase(e.name, p) for p in evaluation) for e in entry.iterdir())
    )


def set_aside(paths: list[Path], output_dir: Path) -> Path | None:
    """Move ``paths`` (an earlier run's outputs that ``overwrite=true`` replaces: :func:`plan_folder`) into
    ``output_dir/.overwritten-<pid>-<token>``, where :func:`put_back_aside` finds them if the new run fails before its
    first iteration and :func:`drop_aside` deletes them once it is done; returns that folder (None: nothing moved).
    """
    if not paths:
        return None
    aside = output_dir / _aside_name()
    aside.mkdir()
    for path in paths:
        log.warning("overwrite=true: the earlier run's %s is deleted after the first iteration", path)
        os.replace(path, aside / path.name)  # a rename in the same folder: nothing is copied
    return aside


def _aside_name() -> str:
    """The name of this process's :func:`set_aside` folder: its pid and a token drawn when the module was imported,
    so that a folder a killed process left under a pid reused since (containers start every entry point under
    the same pid) is never taken for this one's."""
    return f"{ASIDE_PREFIX}{os.getpid()}-{_ASIDE_TOKEN}"


def put_back_aside(output_dir: Path) -> None:
    """Put the outputs this process set aside (:func:`set_aside`) back in ``output_dir``, in place of what the new
    run wrote under the same names."""
    aside = output_dir / _aside_name()  # never another process's, whatever its pid was
    if not aside.is_dir():
        return
    for entry in aside.iterdir():
        dest = output_dir / entry.name
        if dest.is_dir() and not dest.is_symlink():
            shutil.rmtree(dest)
        elif dest.exists() or dest.is_symlink():
            dest.unlink()
        os.replace(entry, dest)
    aside.rmdir()


def drop_aside(aside: Path) -> None:
    """Delete the earlier run's outputs set aside in ``aside`` (the new run has done an iteration)."""
    shutil.rmtree(aside, ignore_errors=True)


class FolderLock:
    """A held :func:`lock_folder` lock; :meth:`release` gives it up (also when the process ends)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path, self.fd = path, fd
        _HELD.append(self)

    def release(self) -> None:
        """Remove the lock file and let the folder go (idempotent)."""
        if self.fd < 0:
            return
        with contextlib.suppress(OSError):
            self.path.unlink()  # while still held: a process waiting on it finds the file gone and retries
        os.close(self.fd)
        self.fd = -1
        _HELD.remove(self)


#: the locks this process holds: a command stopped at once before its run released its own releases them
#: (:func:`put_back_set_up`)
_HELD: list[FolderLock] = []


def lock_folder(folder: Path, setting: str | None = None) -> FolderLock:
    """Lock ``folder`` (created if missing) for this process: an exclusive ``flock`` on
    ``<folder>/.unicorn-train.lock``, which holds the owner's pid and host. The kernel drops the lock when its
    process ends, however it ends, so a lock file left by a dead process is taken over.

    Args:
        folder: the folder to lock.
        setting: the setting that names the folder, said in the refusal (default: :func:`folder_setting`).

    Raises:
        RunFolderBusyError: another live process holds the lock.
    """
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.read(fd, 200).decode(errors="replace").split() or ["?"]
            os.close(fd)
            raise RunFolderBusyError(
                f"{folder} is in use by another unicorn-train (pid {' on '.join(owner[:2])}); wait for it to end "
                f"or train elsewhere ({setting or folder_setting()}=...)"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the owner removed the file while we waited for it: lock the new one
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
    return FolderLock(path, fd)


class FolderChanges:
    """What a run changes in a folder, to undo it when the run fails before its first iteration.

    Create it before the run writes anything, with the names the folder held before this process touched it
    (``entries``; None: it did not exist). :meth:`undo` removes a folder that did not exist before (everything in
    it is the run's), and with it the folders above it up to ``created_top`` (the outermost missing ancestor, which
    the run created with it) that are empty again; in an existing folder it removes only the files and folders the
    run added and restores the records it rewrote (:data:`RUN_RECORDS`), so that the folder is as it was, byte for
    byte (the lines the run appended to ``train.log`` included), and the files named in ``rewritten`` get back the
    bytes given there.
    """

    def __init__(
        self,
        folder: Path,
        entries: set[str] | None,
        created_top: Path | None = None,
        rewritten: Mapping[str, bytes] | None = None,
    ) -> None:
        self.folder, self.existed = folder, entries is not None and folder.is_dir()
        self.created_top = None if created_top is None else created_top.resolve()
        present = self._written() if self.existed else []
        self.paths = {p for p in present if _top(folder, p) in (entries or set())}
        self.records = {p: p.read_bytes() for p in self.paths if p.is_file() and _top(folder, p) in RUN_RECORDS}
        # files of the folder rewritten before this object was made (Hydra's sweep record), by name: their bytes
        self.records |= {folder / name: data for name, data in (rewritten or {}).items() if name in (entries or ())}
        log_file = folder / RUN_LOG
        self.log_size = log_file.stat().st_size if log_file in self.paths and log_file.is_file() else None

    def _written(self) -> list[Path]:
        """What a run can write: the folder's entries, and everything inside its outputs and records."""
        entries = list(self.folder.iterdir())
        return entries + [
            p for e in entries if e.name in RUN_OUTPUTS + RUN_RECORDS and e.is_dir() for p in e.rglob("*")
        ]

    def undo(self) -> None:
        """Put the folder back as it was (see the class docstring), the earlier run's outputs that ``overwrite=true``
        set aside included (:func:`put_back_aside`). Only what a run writes (:data:`RUN_OUTPUTS`,
        :data:`RUN_RECORDS`, :data:`RUN_LOG`) is removed: a file of the user's put in the folder while the run
        started stays, and so does a new folder holding one."""
        if self.existed:
            put_back_aside(self.folder)
        written = self._written() if self.folder.is_dir() else []
        added = [p for p in written if p not in self.paths and _is_run_entry(_top(self.folder, p))]
        for path in sorted(added, key=lambda p: len(p.parts), reverse=True):
            with contextlib.suppress(FileNotFoundError):
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                else:
                    path.unlink()
        if not self.existed:  # the folder, and the ones above it that the run created, where empty again
            folder = self.folder.resolve()
            top = self.created_top
            remove_empty_folders(folder, top if top is not None and folder.is_relative_to(top) else folder)
            return
        for path, data in self.records.items():
            if not path.is_file() or path.read_bytes() != data:
                path.write_bytes(data)
        log_file = self.folder / RUN_LOG
        if self.log_size is not None and log_file.is_file() and log_file.stat().st_size != self.log_size:
            os.truncate(self.folder / RUN_LOG, self.log_size)  # the lines this run appended


def put_back_set_up(folder: Path, entries: set[str] | None, top: Path | None = None) -> None:
    """Undo what a command stopped at once while it set up (a second signal before its run could take the folder
    over, :class:`FolderChanges`) left in ``folder``: the locks this process holds there (:func:`lock_folder`), and
    the logs Hydra opened there that are new (not in ``entries``, the names the folder held before) and still
    empty; then ``folder`` and the folders above it up to ``top`` where it did not exist before (``entries`` None)
    and they are empty again. Nothing else is removed: a folder holding anything more stays as it is."""
    folder = folder.resolve()
    for lock in [lock for lock in _HELD if lock.path.parent.resolve() == folder]:
        lock.release()
    for path in folder.iterdir() if folder.is_dir() else []:
        if path.name in (entries or ()) or path.suffix != ".log" or not _is_run_entry(path.name):
            continue
        with contextlib.suppress(FileNotFoundError):
            if path.is_file() and not path.is_symlink() and path.stat().st_size == 0:
                path.unlink()
    if entries is None:
        remove_empty_folders(folder, top if top is not None and folder.is_relative_to(top) else folder)


def remove_empty_folders(folder: Path, top: Path) -> None:
    """Remove ``folder``, then each folder above it up to ``top`` (included), while they are empty: what another
    process wrote in one keeps it and the folders above it."""
    for made in (folder, *folder.parents):
        if not made.is_relative_to(top):  # above what was created
            return
        try:
            made.rmdir()  # only an empty folder
        except OSError:
            return


def _is_run_entry(name: str) -> bool:
    """Whether a run writes the entry ``name`` at the top of its folder (:data:`_RUN_ENTRIES`)."""
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in _RUN_ENTRIES)


def _top(folder: Path, path: Path) -> str:
    """The name of the entry of ``folder`` that holds ``path``."""
    return path.relative_to(folder).parts[0]


def run_of_checkpoint(path: str | os.PathLike) -> Path | None:
    """The run folder a checkpoint sits in (``<run>/checkpoints/x.ckpt`` -> ``<run>``), or None: an absolute path,
    whether ``path`` is relative (``last.ckpt`` from inside ``checkpoints/``) or a link to the file in the run."""
    for where in (Path(os.path.abspath(path)), Path(path).resolve()):  # the path as named, then the file it names
        if where.parent.name == RUN_OUTPUTS[0]:
            return where.parent.parent
    return None


def run_config(run_dir: Path | None) -> dict[str, Any] | None:
    """``<run>/config.yaml`` (written by ``unicorn-train``) as a dict; None when there is none or it cannot be read
    as such."""
    if run_dir is None or not (run_dir / "config.yaml").is_file():
        return None
    import yaml

    try:
        cfg = yaml.safe_load((run_dir / "config.yaml").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return dict(cfg) if isinstance(cfg, Mapping) else None


def run_dataset(run_dir: Path | None) -> dict[str, Any] | None:
    """The ``dataset`` group of ``<run>/config.yaml`` (written by ``unicorn-train``), if any."""
    dataset = (run_config(run_dir) or {}).get("dataset")
    return dict(dataset) if isinstance(dataset, Mapping) else None
