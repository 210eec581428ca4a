"""Checkpoint files that cannot run code and whose corruption is detected.

Every checkpoint unicorn reads (``unicorn-train`` ``.ckpt``, released UNICORN ``.pkl``, :func:`unicorn.io.save_model`
files, resumed runs) goes through :func:`load_checkpoint_file`, which uses PyTorch's restricted unpickler
(``torch.load(weights_only=True)``): tensors, plain containers and numbers, plus the numpy array types old files hold
(:data:`SAFE_GLOBALS`). A pickle can name any Python callable to be called while it is read (``__reduce__``), so a
file that needs anything else is refused with :class:`UnsafeCheckpointError` instead of being unpickled in full;
for a file you trust, ``trust=True`` (``--trust-checkpoint`` on the command line, ``trust_checkpoint=true`` for
``unicorn-train``) lifts the restriction.

Checkpoints written by unicorn carry a SHA-256 of their content (:func:`seal`, key :data:`INTEGRITY_KEY`): every
tensor's bytes, dtype and shape and every other value, in order. :func:`verify` recomputes it on load, so flipped
bytes that still unpickle are caught (:class:`CorruptCheckpointError`). Files without the key (released files,
checkpoints of older versions) load unchecked.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import io
import os
import pickle
import shutil
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from unicorn.errors import UserError, pid_alive
from unicorn.folders import make_parent_folders
from unicorn.torch_files import NOT_A_TORCH_FILE, load_memory_error, out_of_memory, shortened, torch_file_problem

__all__ = [
    "INTEGRITY_KEY",
    "SAFE_GLOBALS",
    "TRUST_HINT",
    "CheckpointError",
    "CheckpointIsADirectoryError",
    "CheckpointNotAFileError",
    "CheckpointNotFoundError",
    "CorruptCheckpointError",
    "MapLocationError",
    "UnsafeCheckpointError",
    "atomic_save",
    "check_checkpoint_path",
    "check_map_location",
    "content_digest",
    "kind_of",
    "link_into_place",
    "load_checkpoint_file",
    "model_device",
    "remove_stale_temporaries",
    "replacing",
    "seal",
    "temporary_name",
    "verify",
]

#: where :func:`seal` stores the content hash in a checkpoint dict
INTEGRITY_KEY = "unicorn_integrity"

#: how a user allows full unpickling, named in every refusal
TRUST_HINT = "if you trust the file, pass --trust-checkpoint (Python: trust=True; unicorn-train: trust_checkpoint=true)"


def _numpy_globals() -> list[Any]:
    """numpy's array / scalar reconstructors and dtype classes: they build arrays and call nothing else."""
    try:  # numpy 2 renamed np.core; 1.26's numpy._core is a stub whose multiarray is loaded only on import
        from numpy._core import multiarray
    except ImportError:
        from numpy.core import multiarray
    found: list[Any] = [multiarray._reconstruct, multiarray.scalar, np.ndarray, np.dtype]
    found += [type(np.dtype(t)) for t in ("b1", "i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "f2", "f4", "f8")]
    return found


#: globals beyond PyTorch's defaults that checkpoints may name (numpy arrays and scalars of older files)
SAFE_GLOBALS: list[Any] = _numpy_globals()


class CheckpointError(UserError, ValueError):
    """A checkpoint that cannot be read or does not hold a UNICORN model; the message names the file."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint that only full unpickling can read, which can run arbitrary code: refused unless trusted."""


class CorruptCheckpointError(CheckpointError):
    """A checkpoint whose content does not match the hash stored in it."""


class MapLocationError(UserError, ValueError):
    """A ``map_location`` that names no device of this machine: a mistake of the argument, not of the file."""


def check_map_location(map_location: Any) -> Any:
    """``map_location`` when ``torch.load`` can put tensors there, checked before a file is read, so that a device
    this machine lacks is not reported as a file that cannot be read. None, dicts and functions (``torch.load``'s
    remappings) pass unchecked.

    Raises:
        MapLocationError: not a device (``"cpux"``), or a device this machine lacks (``"cuda:7"``, ``"mps"``).
    """
    if map_location is None or isinstance(map_location, Mapping) or callable(map_location):
        return map_location
    not_a_device = MapLocationError(
        f"map_location={map_location!r} is not a device: use 'cpu', 'cuda', 'cuda:N' or a torch.device"
    )
    try:
        device = torch.device(map_location)
    except (RuntimeError, TypeError, ValueError):
        raise not_a_device from None
    stated = str(map_location).rpartition(":")[2]  # torch keeps an index in 8 bits: "cuda:257" is cuda:1
    if device.index is not None and (device.index < 0 or (stated.isdigit() and int(stated) != device.index)):
        raise not_a_device
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (device.index or 0) >= count:
            choice = f"cuda:0 to cuda:{count - 1} or 'cpu'" if count else "'cpu'"
            raise MapLocationError(
                f"map_location={map_location!r}: this machine has {count} CUDA device(s); use {choice}"
            )
    elif device.type not in ("cpu", "meta"):
        try:  # mps, xpu...: whether the backend is there is only known by using it
            torch.empty(0, device=device)
        except Exception as err:  # noqa: BLE001 - backends raise RuntimeError, AssertionError...
            raise MapLocationError(
                f"map_location={map_location!r}: {device.type} is not available on this machine "
                f"({shortened(str(err).split('. ')[0], 100)}); use 'cpu'"
            ) from None
    return map_location


def model_device(map_location: Any) -> torch.device | None:
    """The device a model loaded with ``map_location`` goes to: the one it names, or None for ``torch.load``'s
    remappings (None, a dict, a function), which leave the model where it is built (the CPU). Checked before a file
    is read (:func:`check_map_location`).

    Raises:
        MapLocationError: no device of this machine.
        ValueError: the meta device, which holds no values to load.
    """
    check_map_location(map_location)  # a device this machine lacks is the argument's mistake, not the file's
    if not isinstance(map_location, str | torch.device):
        return None
    device = torch.device(map_location)
    if device.type == "meta":
        raise ValueError("map_location='meta' loads no values: load the model on 'cpu', then move it with .to('meta')")
    return device


def kind_of(value: Any) -> str:
    """What ``value`` is, for the messages that name a checkpoint's field of the wrong type: ``a str``, ``an int``,
    ``a tensor of shape [3]``."""
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {list(value.shape)}"
    name = type(value).__name__
    return f"{'an' if name[0].lower() in 'aeiou' else 'a'} {name}"


def load_checkpoint_file(
    path: str | os.PathLike, map_location: Any = "cpu", trust: bool = False, check: bool = True
) -> Any:
    """``torch.load`` a file with the restricted unpickler (or the full one when ``trust``), then :func:`verify`.

    Args:
        path: the file.
        map_location: passed to ``torch.load``.
        trust: allow full unpickling (only for files from a source you trust: it can run any code).
        check: verify the content hash of sealed dicts.

    Returns:
        the loaded object (the integrity key removed).

    Raises:
        MapLocationError: ``map_location`` is no device of this machine (:func:`check_map_location`), checked
            before the file is read.
        FileNotFoundError: no such file (also a :class:`~unicorn.errors.UserError`).
        UnsafeCheckpointError: the file needs full unpickling and ``trust`` is False.
        CheckpointError: not a readable torch file, or a zip whose entries would inflate beyond the file's size
            (compressed or overlapping entries, which ``torch.save`` never writes), refused from its directory, or
            containers no walk of them finishes (:func:`_containers_problem`), refused before they are walked.
        CorruptCheckpointError: the content hash does not match.
        unicorn.torch_files.TorchFileMemoryError: the memory ran out while reading the file (a ``MemoryError``).
    """
    check_map_location(map_location)
    path = Path(path).expanduser()
    check_checkpoint_path(path)
    unreadable = torch_file_problem(path)
    if unreadable == NOT_A_TORCH_FILE:
        unreadable += " (a unicorn checkpoint, a released UNICORN model, save_model's file)"
    if unreadable:
        raise CheckpointError(f"cannot read checkpoint {path}: {unreadable}")
    try:
        if trust:
            data = torch.load(path, map_location=map_location, weights_only=False)
        else:
            with torch.serialization.safe_globals(SAFE_GLOBALS):
                data = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        names = [] if trust else _unsafe_names(path)
        if not names and (trust or "global" not in str(err).lower()):
            raise CheckpointError(f"cannot read checkpoint {path}: {shortened(err)}") from err
        what = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
        raise UnsafeCheckpointError(
            f"refusing to load {path}: it needs full unpickling ({what or 'objects beyond tensors and plain data'}),"
            f" which can run arbitrary code; {TRUST_HINT}"
        ) from None
    except Exception as err:  # torch raises many kinds (RuntimeError, EOFError...) on bad files
        if out_of_memory(err):  # the machine's fault, not the file's
            raise load_memory_error(path, err) from err
        raise CheckpointError(f"cannot read checkpoint {path}: {type(err).__name__}: {shortened(err)}") from err
    problem = _containers_problem(data)
    if problem:
        raise CheckpointError(f"cannot read checkpoint {path}: {problem}")
    if check and isinstance(data, Mapping):
        data = verify(data, path)
    return data


class CheckpointNotFoundError(UserError, FileNotFoundError):
    """No checkpoint file at the given path."""


class CheckpointIsADirectoryError(UserError, IsADirectoryError):
    """A folder was given where a checkpoint file is expected."""


class CheckpointNotAFileError(CheckpointError):
    """Something other than a regular file or a folder (a device such as ``/dev/zero``, a pipe, a socket) was given
    where a checkpoint file is expected."""


def check_checkpoint_path(path: str | os.PathLike, option: str | None = None) -> Path:
    """``path`` if it is a file; ``option`` (e.g. ``"ckpt_path"``) names where it was given in the message.

    Raises:
        CheckpointIsADirectoryError: ``path`` is a folder.
        CheckpointNotAFileError: ``path`` is not a regular file (a device, a pipe, a socket).
        CheckpointNotFoundError: nothing is there.
    """
    path = Path(path).expanduser()
    if path.is_dir():
        raise CheckpointIsADirectoryError(f"{option or 'checkpoint'}: {path} is a directory, not a checkpoint file")
    if path.exists() and not path.is_file():
        raise CheckpointNotAFileError(
            f"{option or 'checkpoint'}: {path} is not a regular file (a device, pipe or socket), not a checkpoint file"
        )
    if not path.is_file():
        raise CheckpointNotFoundError(
            f"checkpoint not found: {path}" if option is None else f"{option}: no checkpoint file at {path}"
        )
    return path


#: how deep a checkpoint's containers may nest (a model's checkpoint nests a few levels; every reader of one,
#: the content hash included, walks it by recursion)
MAX_CONTAINER_DEPTH = 100

#: how many more items than it holds a checkpoint's containers may show through shared references: a pickle
#: stores a container once and may reference it anywhere, so ``a = [a, a]`` sixty times is a file of a few hundred
#: bytes whose content, as every reader walks it, has 2**60 items
MAX_REPEATED_ITEMS = 1_000_000

_CONTAINERS = (dict, list, tuple, set, frozenset)


class _Refused(Exception):
    """Why :func:`_containers_problem` stopped walking."""


def _containers_problem(data: Any) -> str | None:
    """Why walking the loaded ``data`` would not end (a container that holds itself), overflow the stack (containers
    nested deeper than :data:`MAX_CONTAINER_DEPTH`) or take years (shared containers that repeat more than
    :data:`MAX_REPEATED_ITEMS` items), or None. Only the dicts, lists, tuples and sets a checkpoint is made of are
    walked, each once."""
    expanded: dict[int, int] = {}  # id of a container walked -> items under it, counting every repetition
    on_path: set[int] = set()
    stored = 0  # the items the containers hold, each once

    def walk(value: Any, depth: int) -> int:
        nonlocal stored
        if not isinstance(value, _CONTAINERS):
            return 1
        key = id(value)
        if key in expanded:
            return expanded[key]
        if key in on_path:
            raise _Refused(f"a {type(value).__name__} in it holds itself (a crafted file: walking it would not end)")
        if depth > MAX_CONTAINER_DEPTH:
            raise _Refused(
                f"its containers nest more than {MAX_CONTAINER_DEPTH} levels deep (a crafted file: walking it would "
                "overflow the stack)"
            )
        on_path.add(key)
        items = [v for pair in value.items() for v in pair] if isinstance(value, dict) else value
        total = 1
        for item in items:
            total += walk(item, depth + 1)
            stored += 1
            if total > stored + 1 + MAX_REPEATED_ITEMS:  # bounded before the sums grow out of reach
                raise _Refused(
                    f"its shared containers repeat more than {MAX_REPEATED_ITEMS:,} items (a crafted file: walking it "
                    "would take far longer than reading it)"
                )
        on_path.discard(key)
        expanded[key] = total
        return total

    try:
        walk(data, 0)
    except _Refused as err:
        return str(err)
    return None


def _unsafe_names(path: Path) -> list[str]:
    """The globals a file names beyond the allowed ones (read without unpickling); empty when unknown."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # an old (non-zip) format or a damaged file
        return []
    allowed = {f"{g.__module__}.{g.__qualname__}" for g in SAFE_GLOBALS}
    return [n for n in names if n not in allowed]


# ---------------------------------------------------------------------------------------------- integrity
def _feed(h: Any, value: Any) -> None:
    """Hash ``value`` into ``h``: tensors by dtype, shape and bytes, containers in order, scalars by repr."""
    if isinstance(value, torch.Tensor):
        t = value.detach()
        if t.layout != torch.strided:
            t = t.to_dense()
        t = t.cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}|".encode())
        if t.numel():
            h.update(memoryview(t.reshape(-1).view(torch.uint8).numpy()))
    elif isinstance(value, np.ndarray) and value.dtype != object:
        h.update(f"A{value.dtype.str}{value.shape}|".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, Mapping):
        h.update(f"D{len(value)}|".encode())
        for key, item in value.items():
            _feed(h, key)
            _feed(h, item)
    elif isinstance(value, list | tuple | set | frozenset):
        items = sorted(value, key=repr) if isinstance(value, set | frozenset) else value
        h.update(f"{type(value).__name__[0]}{len(value)}|".encode())
        for item in items:
            _feed(h, item)
    elif value is None or isinstance(value, bool | int | float | complex | str | bytes | torch.dtype | torch.device):
        text = repr(value)
        h.update(f"S{type(value).__name__}{len(text)}|{text}".encode())
    else:  # anything else (only in trusted files): its type and its plain attributes
        h.update(f"O{type(value).__module__}.{type(value).__qualname__}|".encode())
        _feed(h, {k: v for k, v in sorted(getattr(value, "__dict__", {}).items())})


def content_digest(data: Mapping[str, Any]) -> str:
    """SHA-256 hex digest of a checkpoint dict's content, without its :data:`INTEGRITY_KEY` entry."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in data.items() if k != INTEGRITY_KEY})
    return h.hexdigest()


def seal(data: dict[str, Any]) -> dict[str, Any]:
    """Store the content hash of ``data`` in it (in place) under :data:`INTEGRITY_KEY`; returns ``data``."""
    data[INTEGRITY_KEY] = {"algorithm": "sha256", "digest": content_digest(data)}
    return data


def verify(data: Mapping[str, Any], path: str | os.PathLike) -> dict[str, Any]:
    """Check the content hash stored by :func:`seal`, if any; returns a copy of ``data`` without it.

    Raises:
        CorruptCheckpointError: the hash does not match (the message names ``path``).
    """
    data = dict(data)
    stamp = data.pop(INTEGRITY_KEY, None)
    if stamp is None:
        return data
    expected = stamp.get("digest") if isinstance(stamp, Mapping) else None
    if not isinstance(expected, str) or content_digest(data) != expected:
        raise CorruptCheckpointError(
            f"checkpoint {path} is corrupted: its content does not match the SHA-256 stored in it "
            "(a damaged copy or an incomplete transfer); use another copy"
        )
    return data


# ---------------------------------------------------------------------------------------------- writing
def atomic_save(obj: Any, path: str | os.PathLike, sealed: bool = True) -> Path:
    r"""``torch.save(obj, path)`` that never leaves a partial file at ``path``; dicts are sealed (:func:`seal`).

    The object is serialised in memory first, written to ``.<name>.tmp-<pid>`` beside ``path``, flushed to disk
    (``fsync``) and renamed into place (``os.replace`` is atomic). A process killed meanwhile leaves at worst the
    ``.tmp`` file, which the next save to ``path`` deletes (:func:`remove_stale_temporaries`). ``obj`` itself is not
    modified.

    Raises:
        NotADirectoryError: a file stands where a folder above ``path`` goes (:func:`make_parent_folders`).
    """
    path = Path(path)
    make_parent_folders(path)
    remove_stale_temporaries(path.parent, [path.name])
    if sealed and isinstance(obj, Mapping):
        obj = seal(dict(obj))
    buffer = io.BytesIO()
    torch.save(obj, buffer)  # serialise first: a failure here leaves nothing behind
    tmp = temporary_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:
        if err.filename is None and err.errno in DISK_ERRORS:  # a write() on a full disk names no file
            raise type(err)(
                err.errno, f"{err.strerror} while writing {path} (the file there before, if any, is as it was)"
            ) from err
        raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    _sync_folder(path.parent)  # make the rename itself durable
    return path


def link_into_place(source: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Make ``path`` a second name of the complete file ``source``: a hard link made beside ``path`` and renamed into
    place (``os.replace`` is atomic), or, on a file system without hard links, a copy flushed to disk first. A
    process killed meanwhile leaves ``path`` as it was, at worst with a ``.tmp`` file beside it
    (:func:`remove_stale_temporaries`)."""
    source, path = Path(source), Path(path)
    tmp = temporary_name(path)
    try:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        try:
            os.link(source, tmp)
        except OSError:  # no hard links here (some network and FUSE file systems): the bytes are copied
            shutil.copyfile(source, tmp)
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    _sync_folder(path.parent)
    return path


def temporary_name(path: str | os.PathLike) -> Path:
    """Where this process writes ``path`` before renaming it into place: ``.<name>.tmp-<pid>`` beside it, hidden
    (a run folder's own kind of file), and deleted by :func:`remove_stale_temporaries` once its process is gone."""
    path = Path(path)
    return path.with_name(f".{path.name}{TMP_MARK}{os.getpid()}")


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """The :func:`temporary_name` of ``path`` to write in the block, renamed onto ``path`` when the block ends and
    deleted when it raises: ``path`` is always whole, the old file or the new one (logs and tables; checkpoints are
    also flushed to disk, :func:`atomic_save`)."""
    tmp = temporary_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _sync_folder(folder: Path) -> None:
    """Make the renames in ``folder`` durable (where the platform allows)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


#: errors of the disk rather than of a file (a full disk, a quota, a read-only or failing disk): the messages of
#: the writers that meet them name what they were writing
DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO)

#: infix of the temporary files of :func:`atomic_save` (``.<name>.tmp-<pid>``)
TMP_MARK = ".tmp-"


def remove_stale_temporaries(folder: str | os.PathLike, names: Iterable[str] | None = None) -> list[Path]:
    """Delete the ``.tmp-<pid>`` files (:func:`temporary_name`) that writers killed in ``folder`` left behind.

    A file is stale when its process is gone (or is this process, which is not writing now).

    Args:
        folder: the folder.
        names: only the temporaries of these file names (in a folder that holds the user's files too); None: all.

    Returns:
        the deleted files.
    """
    removed = []
    prefixes = [""] if names is None else [f".{name}{TMP_MARK}" for name in names]
    patterns = [f".*{TMP_MARK}*"] if names is None else [f"{glob.escape(prefix)}*" for prefix in prefixes]
    for prefix, pattern in zip(prefixes, patterns):
        for tmp in Path(folder).glob(pattern):
            # a named file's own temporaries only (not those of ``<name>.tmp-1``, which its pattern matches too)
            pid = tmp.name[len(prefix) :] if prefix else tmp.name.rpartition(TMP_MARK)[2]
            if not pid.isdigit() or (int(pid) != os.getpid() and pid_alive(int(pid))) or tmp.is_dir():
                continue  # a live writer's, or a folder: not a temporary file of ours
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed.append(tmp)
    return removed
