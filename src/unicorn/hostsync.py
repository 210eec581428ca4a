"""Whether the code may read the device back (a host synchronisation) in the middle of a training step.

On CUDA a read of a tensor's value on the host (``.item()``, ``bool()``, ``.tolist()``) or an op whose output size
depends on the data (``nonzero``, boolean-mask indexing) makes the host wait until the device has run everything
queued so far: the next kernels are launched only after that, and a step whose model is small is bound by its
launches. Inside ``with sync_free():`` the code that has another way takes it:

- the rasterizer selects into fixed buffers sized by its earlier renders (:mod:`unicorn.render.fixed`,
  :class:`~unicorn.render.rasterizer.MeshRasterizer`), its overflow counted on the device;
- the mesh, pose and colour input checks skip their value reads (face range, finiteness; shapes and dtypes are
  still checked): the trainer runs them on its first iterations only (:mod:`unicorn.lit.module`);
- the neighbour swaps run on every sample with a mask instead of selecting the samples that found neighbours
  (:mod:`unicorn.objectives.neighbors`);
- the trainer takes the texture-averaging probability from the stage callback instead of its buffer, and reads the
  finite-loss flag (:mod:`unicorn.lit.finite`) and the buffers' needs on its logging and checkpoint steps only.

Random numbers for the device are drawn there, inside the block or not, unless a generator elsewhere is given
(:func:`draw_device`). Outside the block (the default, and what the CPU uses) the code keeps its exact algorithms and
reads where it must. The switch is per thread and asyncio task (a :class:`contextvars.ContextVar`).
``torch.compile`` cannot trace a context variable's read: while it traces, the flag is read from a module global that
the blocks keep alongside (the innermost block entered in any thread), which the compiled graph guards on.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import torch

__all__ = ["draw_device", "is_sync_free", "sync_free"]

_SYNC_FREE: ContextVar[bool] = ContextVar("unicorn_sync_free", default=False)
#: the same switch as a global that torch.compile traces (and guards on): the innermost block in any thread
_TRACED = False


def is_sync_free() -> bool:
    """Whether the current code runs inside :func:`sync_free` (enabled)."""
    if torch.compiler.is_compiling():
        return _TRACED
    return _SYNC_FREE.get()


def draw_device(device: torch.device | str, generator: torch.Generator | None = None) -> torch.device:
    """Where to draw random numbers for tensors on ``device``: on ``generator``'s device when one is given (a CPU
    generator gives the same draws on every device, copied to ``device``), else on ``device`` itself, from torch's
    global stream there. A draw on the host for the device is a copy the host waits for, and a host tensor that keeps
    ``torch.compile`` from capturing the code in CUDA graphs."""
    return generator.device if generator is not None else torch.device(device)


@contextmanager
def sync_free(enabled: bool = True) -> Iterator[None]:
    """Take the paths without host reads in this block (``enabled=False``: the default paths)."""
    global _TRACED
    token, traced = _SYNC_FREE.set(bool(enabled)), _TRACED
    _TRACED = bool(enabled)
    try:
        yield
    finally:
        _SYNC_FREE.reset(token)
        _TRACED = traced
