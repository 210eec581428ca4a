"""Fault injection: a callback that SIGKILLs its own training process (the kill-and-resume test), one that raises.

``Kill(step, where)`` kills the process at iteration ``step``:

- ``where="iteration"``: right after the iteration's update, before anything is saved for it;
- ``where="write"``: inside the ``n``-th checkpoint write of that iteration, after part of the bytes reached the
  temporary file and before the rename (``os.fsync`` is where it dies).

It is given to ``unicorn-train`` as ``+callbacks.extra.kill={_target_: tests.lit.faults.Kill, ...}``.
"""

from __future__ import annotations

import os
import signal
from typing import Any

import lightning as L


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


class Kill(L.Callback):
    def __init__(self, step: int, where: str = "iteration", nth_write: int = 1) -> None:
        if where not in ("iteration", "write"):
            raise ValueError(f"where must be iteration or write, got {where!r}")
        self.step, self.where, self.nth_write = step, where, nth_write
        self.writes = 0

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.where != "write":
            return
        io = trainer.strategy.checkpoint_io
        save = io.save_checkpoint

        def save_or_die(checkpoint: dict[str, Any], path: Any, storage_options: Any = None) -> None:
            if trainer.global_step == self.step:
                self.writes += 1
                if self.writes == self.nth_write:
                    real_fsync = os.fsync

                    def fsync_and_die(fd: int) -> None:
                        # half of the file reached the disk: cut it there and die before the rename
                        os.ftruncate(fd, os.fstat(fd).st_size // 2)
                        real_fsync(fd)
                        _die()

                    os.fsync = fsync_and_die
            save(checkpoint, path, storage_options)

        io.save_checkpoint = save_or_die

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.where == "iteration" and trainer.global_step == self.step:
            _die()


class Raise(L.Callback):
    """A bug at iteration ``step``: raises ``ZeroDivisionError`` as the iteration starts."""

    def __init__(self, step: int = 0) -> None:
        self.step = step

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        if trainer.global_step == self.step:
            raise ZeroDivisionError(f"a bug injected at iteration {self.step}")
