"""A signal sent from inside a command, at a chosen call of one of its functions."""

from __future__ import annotations

import os
import signal
import time
from types import ModuleType
from typing import Any

import lightning as L
import pytest


class SignalAtCall:
    """Replaces ``module.name`` for the test (``monkeypatch``): its ``at``-th call sends ``signum`` to this process
    before it runs (``os.kill`` runs the handler before it returns). :attr:`calls` counts the calls.

    Example: ``SignalAtCall(monkeypatch, writer, "_write_model", at=4)``: SIGTERM once three models are written.
    """

    def __init__(
        self, monkeypatch: pytest.MonkeyPatch, module: ModuleType, name: str, at: int, signum: int = signal.SIGTERM
    ) -> None:
        self.wrapped, self.at, self.signum, self.calls = getattr(module, name), at, signum, 0
        monkeypatch.setattr(module, name, self)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        if self.calls == self.at:
            os.kill(os.getpid(), self.signum)
        return self.wrapped(*args, **kwargs)


class SignalAtTrainStart(L.Callback):
    """A callback (``+callbacks.extra.NAME._target_=tests.support.signals.SignalAtTrainStart``) whose
    ``on_train_start``, once every rank has reached it, sends ``signum`` from rank 0 to the process group (as a
    scheduler does: every rank gets it), then works on for ``seconds`` on rank 0 (as the held-out scoring's set-up
    does) while the other ranks wait at the next callback's collective."""

    def __init__(self, signum: int = signal.SIGTERM, seconds: float = 2.0) -> None:
        self.signum, self.seconds = int(signum), float(seconds)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        trainer.strategy.barrier()
        if trainer.global_rank != 0:
            return
        os.killpg(os.getpgid(0), self.signum)
        end = time.monotonic() + self.seconds
        while time.monotonic() < end:  # Python code: each signal's handler runs in it
            time.sleep(0.01)
