"""A CPU oracle for host synchronisations: the ops that would make a CUDA step wait for the device.

On CUDA a read of a tensor's value on the host (``.item()``, ``bool()``, ``float()``, ``.tolist()``, ``.cpu()``)
and the ops whose output size depends on the data (``nonzero``, ``masked_select``, boolean-mask indexing,
``unique``, ``bincount``, ``repeat_interleave`` without ``output_size``) wait for the device. On the CPU they cost
nothing and ``torch.cuda.set_sync_debug_mode`` sees nothing, so :class:`SyncRecorder` records them by name under a
:class:`~torch.utils._python_dispatch.TorchDispatchMode` (and ``tolist``/``cpu``/``numpy``, which do not dispatch on
CPU tensors, by wrapping the methods), whatever the device: a step that records none would not sync on CUDA.
:class:`HostTensorRecorder` records the ops on host tensors in code that runs on another device (the ``meta`` device
stands in for CUDA on the CPU).
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

__all__ = ["HostTensorRecorder", "Sync", "SyncRecorder", "outside", "record_syncs"]

#: aten ops that read the device back (by their overload packet's name)
_ALWAYS = {
    "_local_scalar_dense",  # .item(), bool(), int(), float()
    "nonzero",
    "argwhere",
    "masked_select",
    "unique_consecutive",
    "_unique",
    "_unique2",
    "unique_dim",
    "bincount",
    "histc",
    "equal",
    "allclose",
}
#: ops that sync only with a boolean index (converted to ``nonzero`` on the device)
_BOOL_INDEX = {"index", "index_put", "index_put_", "_index_put_impl_"}
#: ops that make a tensor from Python data (``torch.tensor``), copied to the device where it is made for one
_FROM_HOST_DATA = {"lift_fresh", "lift_fresh_copy"}
#: tensor methods that read the values on the host without dispatching for a CPU tensor
_METHODS = ("tolist", "cpu", "numpy")


@dataclass(frozen=True)
class Sync:
    """One recorded sync: the op's name and the innermost ``unicorn`` source line that called it."""

    op: str
    where: str

    def __str__(self) -> str:
        return f"{self.op} at {self.where}"


def _caller() -> str:
    stack = [f for f in traceback.extract_stack() if not f.filename.endswith("support/syncs.py")]
    ours = [f for f in stack if "/src/unicorn/" in f.filename]
    f = (ours or [f for f in stack if "/torch/" not in f.filename] or stack)[-1]
    return f"{f.filename.rsplit('/src/unicorn/', 1)[-1]}:{f.lineno} ({f.name})"


def _syncs(func: Any, args: tuple, kwargs: dict) -> bool:
    name = func.overloadpacket.__name__
    if name in _ALWAYS:
        return True
    if name == "repeat_interleave":
        return kwargs.get("output_size") is None and isinstance(args[0], torch.Tensor) and len(args) < 3
    if name in _BOOL_INDEX:
        indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
        return any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices)
    return False


@dataclass
class _Recorder(TorchDispatchMode):
    """A dispatch mode that collects :class:`Sync` records in :attr:`syncs`."""

    syncs: list[Sync] = field(default_factory=list)

    def __post_init__(self) -> None:
        super().__init__()


@dataclass
class SyncRecorder(_Recorder):
    """Records every syncing op run inside it (see the module docstring) in :attr:`syncs`; with ``host_data``, also
    the tensors made from host data (``torch.tensor(value, device=...)``: on CUDA a copy the host waits for)."""

    host_data: bool = False

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        if _syncs(func, args, kwargs) or (self.host_data and name in _FROM_HOST_DATA):
            self.syncs.append(Sync(name, _caller()))
        return func(*args, **kwargs)


class HostTensorRecorder(_Recorder):
    """Records every op run inside it that takes or returns a tensor on the host (``cpu``) in :attr:`syncs`.

    For code whose inputs live on another device (the ``meta`` device runs the same Python on CPU-only machines): a
    tensor on the host (made there, or a constant of a module) is copied to the device where it is used, a copy the
    host waits for, and it keeps CUDA graphs from capturing the code (``torch.compile`` skips them for graphs with
    host tensors).
    """

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        out = func(*args, **(kwargs or {}))
        if any(isinstance(t, torch.Tensor) and t.device.type == "cpu" for t in tree_leaves((args, kwargs, out))):
            self.syncs.append(Sync(func.overloadpacket.__name__, _caller()))
        return out


def _wrapped(recorder: SyncRecorder, name: str, method: Callable) -> Callable:
    def read(self: torch.Tensor, *args: Any, **kwargs: Any) -> Any:
        recorder.syncs.append(Sync(name, _caller()))
        return method(self, *args, **kwargs)

    return read


@contextmanager
def record_syncs(host_data: bool = False) -> Iterator[SyncRecorder]:
    """``with record_syncs() as rec:`` records the host syncs of the block in ``rec.syncs`` (``host_data``: and the
    tensors made from host data, :class:`SyncRecorder`)."""
    recorder = SyncRecorder(host_data=host_data)
    saved = {name: getattr(torch.Tensor, name) for name in _METHODS}
    for name, method in saved.items():
        setattr(torch.Tensor, name, _wrapped(recorder, name, method))
    try:
        with recorder:
            yield recorder
    finally:
        for name, method in saved.items():
            setattr(torch.Tensor, name, method)


def outside(syncs: list[Sync], files: tuple[str, ...] = ()) -> list[str]:
    """The syncs (as text) not made in ``files`` (paths under ``src/unicorn``; none: every sync)."""
    return [str(s) for s in syncs if not (files and s.where.startswith(files))]
