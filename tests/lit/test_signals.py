"""Signals outside the training iterations: :func:`unicorn.lit.signals.interrupt_on_signal`."""

from __future__ import annotations

import os
import signal

import pytest

from unicorn.errors import Interrupted
from unicorn.lit.signals import interrupt_on_signal


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_in_the_block_raises_interrupted_and_the_next_one_acts_as_before(signum):
    seen = []
    before = signal.signal(signum, lambda s, frame: seen.append(s))
    try:
        with interrupt_on_signal("while testing"):
            with pytest.raises(Interrupted) as caught:
                os.kill(os.getpid(), signum)  # os.kill runs the handlers of its own process before it returns
            assert str(caught.value) == f"stopped by {signal.Signals(signum).name} while testing"
            assert caught.value.exit_status == 128 + signum
            os.kill(os.getpid(), signum)  # the second: the handler from before the block
        assert seen == [signum]
        os.kill(os.getpid(), signum)  # after the block: the handler from before it
        assert seen == [signum, signum]
    finally:
        signal.signal(signum, before)


def test_the_handlers_from_before_the_block_are_back_after_it():
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    with interrupt_on_signal("while testing"):
        assert all(signal.getsignal(s) is not h for s, h in before.items())
    assert {s: signal.getsignal(s) for s in before} == before
    with pytest.raises(ValueError, match="boom"), interrupt_on_signal("while testing"):
        raise ValueError("boom")
    assert {s: signal.getsignal(s) for s in before} == before
