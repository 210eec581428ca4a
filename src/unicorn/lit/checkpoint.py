"""Checkpoints that are either complete or absent.

:class:`AtomicCheckpointIO` writes a checkpoint to a temporary file next to its destination, flushes it to
disk (``fsync``) and renames it into place (``os.replace`` is atomic on POSIX and Windows). A run killed while
saving (Ctrl-C, SIGKILL, a pre-empted job) leaves its previous checkpoint intact, at worst with a stray
``.tmp`` file beside it. Lightning's own writer renames too (fsspec transactions) but does not ``fsync``, so a
crash of the machine could leave a renamed but incomplete file. Remote paths (``s3://``...) go to Lightning's
writer.
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

__all__ = ["AtomicCheckpointIO", "atomic_torch_save"]


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save(obj, path)`` that never leaves a partial file at ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    torch.save(obj, buffer)  # serialise first: a failure here leaves nothing behind
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    # make the rename itself durable
    with contextlib.suppress(OSError):
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint I/O with atomic, fsync'ed local writes (pass it in ``Trainer(plugins=[...])``)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        atomic_torch_save(checkpoint, path)
