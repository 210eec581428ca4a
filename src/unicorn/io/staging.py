"""Output folders that are complete or absent: written to a temporary sibling, moved into place at the end.

:func:`staged_folder` is how ``unicorn-eval`` and ``unicorn-reconstruct`` write their output folders: a run that
fails part-way (a full disk, a bad image, Ctrl-C) leaves the folder as it was, not half-written. The sibling
``.<name>.partial-<pid>`` lies on the same file system, so moving its entries into place is a rename (an existing
folder whose parent cannot be written to, such as a mount point, holds it inside instead); one left by a killed
process is removed by the next run that writes the same folder. :func:`check_writable` tells before any work
whether the folder can be written.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path, PurePosixPath

from unicorn.errors import UserError, pid_alive, signals_held
from unicorn.io.serialization import DISK_ERRORS

__all__ = ["PARTIAL_MARK", "OutputConflictError", "check_replaceable", "check_writable", "staged_folder"]

#: infix of the temporary siblings (``.<name>.partial-<pid>``)
PARTIAL_MARK = ".partial-"


def _remove_stale_siblings(out: Path) -> None:
    """Remove the temporary folders of ``out`` (beside it or inside it) left by processes that no longer run."""
    prefix = f".{out.name}{PARTIAL_MARK}"
    for folder in (out.parent, out):
        if not _is_folder(folder):
            continue
        for sibling in folder.iterdir():
            pid = sibling.name[len(prefix) :]
            if sibling.name.startswith(prefix) and pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(sibling, ignore_errors=True)


def _absolute(out: str | os.PathLike) -> Path:
    """``out`` made absolute, ``.`` and ``..`` kept by their names (the temporary folder's name needs one)."""
    out = Path(os.path.abspath(Path(out).expanduser()))
    if not out.name:
        raise OutputConflictError(f"cannot write the output folder {out}: choose a folder below it")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"output folder {out} exists and is not a folder")
    above = next((folder for folder in out.parents if folder.exists()), None)
    if above is not None and not above.is_dir():
        raise NotADirectoryError(f"cannot write the output folder {out}: {above} is a file, not a folder")
    return out


def _make_staging(out: Path) -> Path:
    """Create the empty temporary folder of ``out``: beside it, or inside an existing ``out`` whose parent cannot be
    written to (a mount point)."""
    name = _staging_name(out)
    places = [out.parent] + ([out] if _is_folder(out) else [])
    for k, place in enumerate(places):
        tmp = place / name
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            tmp.mkdir()
            return tmp
        except OSError as err:
            if k == len(places) - 1 or err.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
                raise _write_error(out, err) from err
    raise AssertionError("unreachable")


def _staging_name(out: Path) -> str:
    """The name of ``out``'s temporary folder (hidden, marked as partial, this process's)."""
    return f".{out.name}{PARTIAL_MARK}{os.getpid()}"


def _write_error(out: Path, err: OSError) -> OSError:
    """``err`` as the error of a command that cannot write its output folder ``out``."""
    return type(err)(err.errno, f"cannot write the output folder {out}: {err.strerror}")


def _probe(out: Path, probe: Path, folder: bool) -> None:
    """Make and remove ``probe``, a folder or a file, as writing ``out`` would; an error names ``out``."""
    try:
        if folder:
            probe.mkdir()
            probe.rmdir()
        else:
            probe.touch()
            probe.unlink()
    except OSError as err:
        raise _write_error(out, err) from err


def check_writable(out: str | os.PathLike) -> None:
    """Check before any work that :func:`staged_folder` can write ``out``: its temporary folder can be made and,
    where ``out`` exists, files can be written into it.

    Raises:
        OSError: the message names ``out`` (a read-only disk, a missing permission, a file where a folder is
            needed on the way).
        OutputConflictError, NotADirectoryError: as :func:`staged_folder`.
    """
    out = _absolute(out)
    if out.parent.is_dir():
        _make_staging(out).rmdir()
    else:  # the folders above it are made when it is written: the nearest existing one must take a new folder
        above = next(folder for folder in out.parents if folder.exists())
        _probe(out, above / _staging_name(out), folder=True)
    if _is_folder(out):
        _probe(out, out / f"{_staging_name(out)}.probe", folder=False)


class OutputConflictError(UserError, FileExistsError):
    """The output folder holds what the command would replace or cannot write over: a file where it writes a folder,
    a folder where it writes a file, or (without ``overwrite``) an earlier run's outputs."""


def _is_folder(path: Path) -> bool:
    return path.is_dir() and not path.is_symlink()


def _conflict(dest: Path, folder: bool) -> str | None:
    """How ``dest`` keeps an output (a folder where ``folder``, else a file) from replacing it (``"<path> is a link
    where a folder goes"``), or None: a file or a link where a folder goes, a folder where a file goes."""
    if folder and (dest.exists() or dest.is_symlink()) and not _is_folder(dest):
        return f"{dest} is {'a link' if dest.is_symlink() else 'a file'} where a folder goes"
    if not folder and _is_folder(dest):
        return f"{dest} is a folder where a file goes"
    return None


def _conflicts(source: Path, target: Path) -> list[str]:
    """The entries of ``target`` that ``source``'s entries cannot replace, each described (:func:`_conflict`)."""
    found = []
    for entry in sorted(source.iterdir()):
        dest = target / entry.name
        if _is_folder(entry) and _is_folder(dest):
            found += _conflicts(entry, dest)
        elif (conflict := _conflict(dest, _is_folder(entry))) is not None:
            found.append(conflict)
    return found


def _conflict_error(out: Path, conflict: str) -> OutputConflictError:
    message = f"cannot write the output folder {out}: {conflict}; move it away or choose another folder"
    return OutputConflictError(message)


def check_replaceable(out: str | os.PathLike, folders: Sequence[str] = (), files: Sequence[str] = ()) -> None:
    """Refuse, before any work, what :func:`staged_folder` would refuse once it is done: an entry of an existing
    ``out`` that the outputs ``folders`` and ``files`` (names in ``out``) cannot replace.

    Raises:
        OutputConflictError: names the first such entry, in :func:`staged_folder`'s words.
    """
    if not _is_folder(Path(out)):
        return
    where = _absolute(out)
    for names, folder in ((folders, True), (files, False)):
        for name in names:
            conflict = _conflict(where / name, folder)
            if conflict is not None:
                raise _conflict_error(where, conflict)


def _own_folder(pattern: str) -> str | None:
    """The folder a pattern of ``outputs`` names without wildcards (``report`` of ``report/sample*``), which is the
    command's own; None for the top level or a folder part with wildcards (``*/turntable.gif``)."""
    folder = PurePosixPath(pattern).parent.as_posix()
    return None if folder == "." or glob.has_magic(folder) else folder


def _outdated(source: Path, target: Path, outputs: Sequence[str]) -> list[Path]:
    """The files in ``target`` that match the glob patterns ``outputs`` (the command's own), where ``source`` has
    none of that name, in folders that ``source`` writes too or that the pattern names without wildcards
    (:func:`_own_folder`): an earlier run's, which this one did not write. A folder matching a pattern is not one:
    the commands' outputs are files, so it is a user's, and kept."""
    found = []
    for pattern in outputs:
        own = _own_folder(pattern) is not None
        for path in target.glob(pattern):
            if source in path.parents or _is_folder(path):  # the temporary folder itself (it may lie in ``target``)
                continue
            rel = path.relative_to(target)
            if (own or _is_folder(source / rel.parent)) and not (source / rel).exists():
                found.append(path)
    return sorted(set(found))


def _remove_emptied_folders(target: Path, outputs: Sequence[str]) -> None:
    """Remove the folders the patterns ``outputs`` name (:func:`_own_folder`) that hold nothing any more: a user's
    file in one keeps it."""
    for folder in sorted({f for f in map(_own_folder, outputs) if f}, key=len, reverse=True):
        path = target / folder
        if _is_folder(path) and not any(path.iterdir()):
            path.rmdir()


def _merge(source: Path, target: Path) -> None:
    """Move ``source``'s entries into the folder ``target``: files replace same-named files, folders are merged
    (:func:`_conflicts` must be empty)."""
    for entry in sorted(source.iterdir()):
        dest = target / entry.name
        if _is_folder(entry) and _is_folder(dest):
            _merge(entry, dest)
        else:
            _move(entry, dest)


def _move(entry: Path, dest: Path) -> None:
    """Rename ``entry`` to ``dest``; where ``dest`` is on another file system (an output folder that is a mount
    point, or a link to a folder elsewhere), copy it beside ``dest`` first and rename the copy, so that ``dest``
    is still replaced whole."""
    try:
        os.replace(entry, dest)
        return
    except OSError as err:
        if err.errno != errno.EXDEV:
            raise
    copy = dest.with_name(f".{dest.name}{PARTIAL_MARK}{os.getpid()}.copy")  # not the staging folder's name
    try:
        if _is_folder(entry):
            shutil.copytree(entry, copy, symlinks=True)
        else:
            shutil.copy2(entry, copy, follow_symlinks=False)
        os.replace(copy, dest)
    finally:
        if copy.is_dir() and not copy.is_symlink():
            shutil.rmtree(copy, ignore_errors=True)
        elif copy.exists() or copy.is_symlink():
            copy.unlink()
    shutil.rmtree(entry) if _is_folder(entry) else entry.unlink()


@contextlib.contextmanager
def staged_folder(out: str | os.PathLike, outputs: Sequence[str] = (), *, merge: bool = True) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``out``; when the block succeeds, move its contents into ``out``.

    A missing ``out`` is the renamed temporary folder. In an existing ``out`` each file written replaces the file
    of the same name (sub-folders are merged) and the others are kept: whether an existing folder may be written
    into is the caller's decision; only the files matching ``outputs`` (glob patterns relative to ``out``: the
    command's own optional outputs, such as a turntable made only on request) that an earlier run wrote
    in a folder this block writes again, or in a folder a pattern names without wildcards (``report`` of
    ``report/sample*``), and this block did not write, are removed, so that a folder does not mix two runs; such a
    named folder left empty is removed too.
    With ``merge`` False, ``out`` must still be missing or empty when the files move: the caller checked it before
    the work began, and another process may have written it since.
    When the block raises, the temporary folder is removed and ``out`` is untouched. A SIGTERM or Ctrl-C that comes
    while the files move is held until they are all in place (:func:`~unicorn.errors.signals_held`).

    Raises:
        OSError: the temporary folder cannot be created (a read-only or full disk, a missing permission).
        OutputConflictError: an entry of ``out`` is a file where a folder is written or a folder where a file is,
            or ``merge`` is False and ``out`` is no longer empty (nothing is moved: ``out`` is as it was).
    """
    out = _absolute(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_siblings(out)
    tmp = _make_staging(out)
    try:
        yield tmp
        with signals_held():  # a Ctrl-C or SIGTERM now stops the command once every file is in place
            if not out.exists():
                _move(tmp, out)
                return
            if not merge and _is_folder(out) and any(entry != tmp for entry in out.iterdir()):  # tmp: may lie in out
                raise OutputConflictError(
                    f"the output folder {out} was written by another command while this one ran; nothing was moved "
                    "into it: run again with another folder, or with --overwrite to write into it"
                )
            conflicts = _conflicts(tmp, out)
            if conflicts:  # checked before anything moves: the folder is updated whole or not at all
                raise _conflict_error(out, conflicts[0])
            outdated = _outdated(tmp, out, outputs)
            _merge(tmp, out)
            for path in outdated:
                path.unlink(missing_ok=True)
            _remove_emptied_folders(out, outputs)
    except OSError as err:
        if err.filename is None and err.errno in DISK_ERRORS:  # e.g. a write() on a full disk names no file
            raise type(err)(err.errno, f"{err.strerror} while writing the output folder {out}") from err
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
