"""What unicorn checks in a file before ``torch.load`` reads it.

``torch.load`` inflates a zip's compressed entries, and allocates the storages an old-format file declares, before
anything can be checked: :func:`torch_file_problem` reads only the file's directory or declarations, so that a file
of a few hundred bytes cannot fill the memory. Every file unicorn gives to ``torch.load`` passes it first
(checkpoints, released models, VGG16 weights, Pascal3D+ point clouds); :func:`read_plain` reads the files of plain
tensors and containers (weights, point clouds) through it.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from unicorn.errors import UserError

__all__ = [
    "NOT_A_TORCH_FILE",
    "TorchFileError",
    "TorchFileMemoryError",
    "load_memory_error",
    "out_of_memory",
    "read_plain",
    "shortened",
    "torch_file_problem",
]

#: how files written by ``torch.save`` begin: a zip archive, or (the format before torch 1.6) a pickle of this
#: magic number
_ZIP_HEAD = b"PK\x03\x04"
_LEGACY_MAGIC = (0x1950A86A20F9469CFC6C).to_bytes(10, "little")


NOT_A_TORCH_FILE = "it is not a file written by torch.save"


def torch_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` must not be given to ``torch.load`` (empty, neither format of ``torch.save``, or a zip that would
    inflate in memory, :func:`_inflating_zip`), or None. Every file unicorn reads with ``torch.load`` passes here
    first: checkpoints, weights, point clouds."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(32)
    except OSError:
        return None  # torch.load says what is wrong
    if not head:
        return "the file is empty"
    if head.startswith(_ZIP_HEAD):
        return _inflating_zip(path)
    if head.startswith(b"\x80") and _LEGACY_MAGIC in head:
        return _oversized_legacy(path)
    return NOT_A_TORCH_FILE


def _inflating_zip(path: Path) -> str | None:
    """Why a zip checkpoint would inflate in memory beyond its size, read from its directory only, or None.

    ``torch.load`` inflates compressed entries before anything can be checked: a file of 0.5 MB can become 512 MB
    (a decompression bomb). ``torch.save`` stores every entry uncompressed and once, so compressed entries, or
    entries declaring more bytes than the file holds (entries that overlap), mean a file made or re-packed by
    something else.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            entries = archive.infolist()
    except zipfile.BadZipFile as err:
        return f"it is a damaged zip archive, a truncated file or an incomplete copy (zipfile: {shortened(err, 120)})"
    except OSError:
        return None  # torch.load says what is wrong
    compressed = next((e for e in entries if e.compress_type != zipfile.ZIP_STORED), None)
    if compressed is not None:
        return (
            f"its entry {compressed.filename!r} is compressed, which torch.save never does (a re-packed file, which "
            "could inflate to any size in memory); save it again with torch.save"
        )
    declared, size = sum(e.file_size for e in entries), path.stat().st_size
    if declared > size:
        return (
            f"its entries declare {declared:,} bytes, more than the {size:,} bytes of the file (overlapping entries, "
            "which torch.save never writes and which could fill the memory)"
        )
    return None


#: bytes per element of the typed storages the format before PyTorch 1.6 names (others count one byte)
_LEGACY_ELEMENT_BYTES = {
    "DoubleStorage": 8, "FloatStorage": 4, "HalfStorage": 2, "BFloat16Storage": 2, "LongStorage": 8,
    "IntStorage": 4, "ShortStorage": 2, "CharStorage": 1, "ByteStorage": 1, "BoolStorage": 1,
    "ComplexDoubleStorage": 16, "ComplexFloatStorage": 8,
}  # fmt: skip


class _Named:
    """What :class:`_DeclarationReader` puts where a pickle names a global: the name, never the object. It takes
    what a pickle gives the objects it builds (a state, the items of an ``OrderedDict``, the elements of a list
    subclass) and keeps none of it."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        pass

    def __setitem__(self, key: Any, value: Any) -> None:
        pass

    def append(self, value: Any) -> None:
        pass

    def extend(self, values: Any) -> None:
        pass


class _DeclarationReader(pickle.Unpickler):
    """Reads a pickle without calling anything it names: every global is a :class:`_Named` stand-in, and each
    persistent id (a storage's declaration in ``torch.save``'s old format) is collected in :attr:`declared`."""

    def __init__(self, file: Any) -> None:
        super().__init__(file)
        self.declared: dict[Any, int] = {}

    def find_class(self, module: str, name: str) -> type:
        return type(name, (_Named,), {})

    def persistent_load(self, pid: Any) -> None:
        if isinstance(pid, tuple) and len(pid) >= 5 and pid[0] == "storage" and isinstance(pid[4], int):
            element = _LEGACY_ELEMENT_BYTES.get(getattr(pid[1], "__name__", ""), 1)
            key = repr(pid[2])
            self.declared[key] = max(self.declared.get(key, 0), pid[4] * element)


def _oversized_legacy(path: Path) -> str | None:
    """Why a file in ``torch.save``'s format before PyTorch 1.6 must not be read, or None.

    That format declares each tensor storage's size before its bytes, and ``torch.load`` allocates every storage at
    its declared size before reading it: a file of a few hundred bytes can ask for terabytes. The declarations are
    read here with nothing called; their total must fit in the file, which holds every storage's bytes.
    """
    reader = None
    try:
        with path.open("rb") as f:
            for _ in range(4):  # magic number, protocol version, system info, then the object with its storages
                reader = _DeclarationReader(f)
                reader.load()
    except Exception:  # a damaged file: torch.load says what is wrong
        return None
    declared, size = sum(reader.declared.values()), path.stat().st_size
    if declared > size:
        return (
            f"its tensors declare {declared:,} bytes, more than the {size:,} bytes of the file (a damaged or crafted "
            "file in the format before PyTorch 1.6, which would allocate them all before reading)"
        )
    return None


def shortened(text: object, limit: int = 300) -> str:
    """``text`` on one line (whitespace runs made one space), cut to ``limit`` characters with ``...``."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


class TorchFileError(ValueError):
    """Why a file of plain tensors cannot be read (:func:`read_plain`): one line, without the file's name, for the
    caller's message to name it."""


class TorchFileMemoryError(UserError, MemoryError):
    """The memory ran out while ``torch.load`` read a file (the machine's, or the device's the tensors go to): the
    message names the file and its size, and does not blame the file, which :func:`torch_file_problem` has checked
    holds no more than its size."""


#: how torch's allocators say that memory ran out in the ``RuntimeError`` they raise (CPU on Linux and Windows, CUDA,
#: MPS)
_OUT_OF_MEMORY = ("can't allocate memory", "not enough memory", "out of memory")


def out_of_memory(err: BaseException) -> bool:
    """Whether an error ``torch.load`` raised says that the memory ran out, not that the file is bad."""
    if isinstance(err, (MemoryError, torch.OutOfMemoryError)):
        return True
    return isinstance(err, RuntimeError) and any(words in str(err) for words in _OUT_OF_MEMORY)


def load_memory_error(path: str | os.PathLike, err: BaseException) -> TorchFileMemoryError:
    """The one-line error for running out of memory (:func:`out_of_memory`) while loading ``path``."""
    try:
        size = f" ({Path(path).stat().st_size:,} bytes)"
    except OSError:
        size = ""
    detail = shortened(err, 200) or type(err).__name__
    return TorchFileMemoryError(
        f"ran out of memory loading {path}{size}: {detail}; free some memory, or load it where more is available"
    )


def read_plain(path: str | os.PathLike) -> Any:
    """``torch.load`` of a file of tensors and plain containers, on the CPU, after :func:`torch_file_problem`, with
    nothing unpickled that could run code (``weights_only``).

    Raises:
        TorchFileError: the problem :func:`torch_file_problem` found, or torch's error on one line.
        TorchFileMemoryError: the memory ran out while reading the file (the message names it).
    """
    problem = torch_file_problem(path)
    if problem is None:
        try:
            return torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:  # noqa: BLE001 - torch's errors for bad bytes vary (zip, pickle, EOF)
            if out_of_memory(err):
                raise load_memory_error(path, err) from err
            problem = shortened(err, 200) or type(err).__name__
    raise TorchFileError(problem)
