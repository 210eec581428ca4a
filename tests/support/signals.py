"""A signal sent from inside a command, at a chosen call of one of its functions."""

from __future__ import annotations

import os
import signal
from types import ModuleType
from typing import Any

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
