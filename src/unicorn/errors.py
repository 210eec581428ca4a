"""The one exception family for mistakes a user can fix (a missing file, a bad option, an unsafe checkpoint), the
one for commands stopped by a signal, and the one warning family for what a user should know but need not stop
for (:class:`UnicornWarning`).

Command-line entry points report a :class:`UserError` in one line on stderr with exit status 2; anything else is
a bug and keeps its traceback. Library code raises the most specific subclass it has; each subclass also derives
from the built-in exception callers already catch (``ValueError``, ``FileNotFoundError``...). Inside
:func:`interrupt_on_signal`, SIGTERM and SIGINT raise :class:`Interrupted`; inside :func:`signals_held` they wait
for the block's end.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, ClassVar

__all__ = [
    "Interrupted",
    "MissingPackageError",
    "UnicornWarning",
    "UserError",
    "defer_stop_signals",
    "ignore_stop_signals",
    "import_open3d",
    "interrupt_on_signal",
    "pid_alive",
    "pending_interrupt",
    "signals_held",
]

#: the signals that stop a command: Ctrl-C and a scheduler's or ``kill``'s request
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: the stop signals the process was started ignoring (read at the first import, before unicorn sets any): a script's
#: background job ignores Ctrl-C, and by the shells' convention it stays ignored, whatever unicorn handles
IGNORED_AT_START = frozenset(s for s in STOP_SIGNALS if signal.getsignal(s) is signal.SIG_IGN)


class UserError(Exception):
    """A mistake in the user's input or environment; the message says what is wrong and how to fix it."""


class MissingPackageError(UserError, ImportError):
    """An optional package that a feature needs is not installed; the message says how to install it."""


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (one of another user's included): a signal 0 probe."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists, owned by someone else
    return True


def import_open3d() -> Any:
    """Import open3d (ray casting for the synthetic renders, voxelisation for the 3D IoU), with the system library
    it needs named when it cannot load: its Linux wheels link libusb-1.0, which minimal images lack.

    Raises:
        MissingPackageError: open3d or a library it loads is missing.
    """
    try:
        import open3d
    except (ImportError, OSError) as err:  # a missing shared library surfaces as either
        missing = "libusb-1.0" in str(err)
        hint = (
            "install the system library libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0)"
            if missing
            else "pip install open3d"
        )
        raise MissingPackageError(f"open3d cannot be loaded ({err}): {hint}") from err
    return open3d


class UnicornWarning(UserWarning):
    """Something a user should know that does not stop the command (a render that dropped faces, a collapsed
    viewpoint, a compiler that cannot run); the message says what to do about it.

    The command-line programs log these in one line, ``<Class>: <message>``, at the class's :attr:`level`, on the
    console and into a run's ``train.log`` (:func:`unicorn.cli.errors.log_warnings`); in Python they are ordinary
    warnings, filtered as usual (``warnings.filterwarnings``, ``-W``, ``PYTHONWARNINGS``).
    """

    #: the logging level the command-line programs log it at
    level: ClassVar[int] = logging.WARNING


class Interrupted(Exception):
    """A command stopped early by a signal (SIGTERM, SIGINT) after saving what it needs to go on.

    Command-line entry points print the message on one line and exit with :attr:`exit_status` (``128 + signal``,
    as a shell reports a process killed by that signal), not 0: a scheduler sees that the job did not finish.
    """

    def __init__(self, message: str, exit_status: int) -> None:
        super().__init__(message)
        self.exit_status = exit_status


#: the signals received in the :func:`interrupt_on_signal` blocks under way, one list per block (innermost last)
_RECEIVED: list[list[int]] = []
#: the signals :func:`defer_stop_signals` noted before a command could stop cleanly, oldest first
_DEFERRED: list[int] = []


def defer_stop_signals(prog: str | None = None) -> None:
    """From now on, until an :func:`interrupt_on_signal` block takes them over, note SIGTERM and SIGINT instead of
    dying of them (the default), so that a command still setting up (importing, composing its config, creating its
    folders) can put its folders back before it stops: :func:`pending_interrupt` reports the noted signal. A second
    one meanwhile stops the process at once (exit status ``128 + signal``), saying so on stderr: ``<prog>: stopped
    by SIGTERM at once ...`` (the program's file name without ``prog``). Ignored signals stay ignored; outside the
    main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        return

    def note(signum: int, frame: Any) -> None:
        if _DEFERRED:
            name = signal.Signals(signum).name
            who = prog or os.path.basename(sys.argv[0])
            print(f"{who}: stopped by {name} at once (signalled twice while setting up)", file=sys.stderr, flush=True)
            raise SystemExit(128 + signum)
        _DEFERRED.append(signum)

    for signum in STOP_SIGNALS:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, note)


def _interrupted(signum: int, where: str) -> Interrupted:
    name = signal.Signals(signum).name
    return Interrupted(f"stopped by {name} {where}" if where else f"stopped by {name}", 128 + signum)


def pending_interrupt(where: str = "") -> Interrupted | None:
    """The :class:`Interrupted` of a signal that came in an :func:`interrupt_on_signal` block still under way (or
    that :func:`defer_stop_signals` noted before), or None. The error the signal raised can be swallowed by code that
    catches every ``Exception`` (a logging handler's ``emit``); the stop is not: the code that goes on asks here
    (the training, before its first iteration), and the block raises it again when it ends."""
    signals = [*_DEFERRED, *(s for block in _RECEIVED for s in block)]
    return _interrupted(signals[0], where) if signals else None


@contextmanager
def interrupt_on_signal(where: str = "") -> Iterator[None]:
    """In this block SIGTERM and SIGINT raise :class:`Interrupted` at once: ``stopped by SIGTERM <where>``, exit
    status ``128 + signal``. The handlers before the block are back after it, and after the first signal (a second
    one acts as it would outside the block). A signal whose error was swallowed inside the block (see
    :func:`pending_interrupt`), or turned into another error, raises it when the block ends. Training inside the
    block still stops at a step boundary: :class:`unicorn.lit.signals.GracefulStop` takes the signals over while
    the trainer runs. Outside the main thread (where Python cannot set handlers) the block changes nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous: dict[int, Any] = {}
    received: list[int] = []

    def interrupt(signum: int, frame: Any) -> None:
        restore_handlers(previous)
        received.append(signum)
        raise _interrupted(signum, where)

    previous.update(handle_stop_signals(interrupt))
    _RECEIVED.append(received)
    try:
        yield
    except Interrupted:
        raise
    except Exception as err:
        if received:  # the signal's error became another on its way (a reader that wraps whatever fails in it)
            raise _interrupted(received[0], where) from err
        raise
    else:
        if received:  # the error was swallowed on its way: the command still stops
            raise _interrupted(received[0], where)
    finally:
        restore_handlers(previous)
        _RECEIVED[:] = [block for block in _RECEIVED if block is not received]  # by identity: [] == []


@contextmanager
def signals_held() -> Iterator[None]:
    """SIGTERM and SIGINT that arrive in this block wait for its end; then each kind that arrived is delivered once,
    in the order they came, to the handlers from before the block (:func:`interrupt_on_signal`'s raises
    :class:`Interrupted` there; Python's default for SIGTERM ends the process). For the few steps that must not be
    cut half-way: moving an output folder's files into place, putting a failed run's folder back as it was. Outside
    the main thread (where Python cannot set handlers) the block changes nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum: int, frame: Any) -> None:
        if signum not in held:
            held.append(signum)

    previous = handle_stop_signals(hold)
    try:
        yield
    finally:
        restore_handlers(previous)
        for signum in held:
            signal.raise_signal(signum)  # runs the restored handler before it returns


def handle_stop_signals(handler: Any) -> dict[int, Any]:
    """Give :data:`STOP_SIGNALS` to ``handler`` (main thread only), but those :data:`IGNORED_AT_START`; returns the
    handlers they had, for :func:`restore_handlers`."""
    return {signum: signal.signal(signum, handler) for signum in STOP_SIGNALS if signum not in IGNORED_AT_START}


def ignore_stop_signals(worker_id: int = 0) -> None:
    """A DataLoader's ``worker_init_fn``: the worker ignores :data:`STOP_SIGNALS`, which the command's process
    handles (a step boundary, a clean stop). Ctrl-C, SLURM's ``scancel`` and ``kill -- -PGID`` signal the whole
    process group: a worker that died of it would end the command with the loader's error, before the iteration
    under way is saved. Workers still end with the command: it stops them, and they leave when it is gone."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


def restore_handlers(previous: dict[int, Any]) -> None:
    """Give each signal of ``previous`` (:func:`handle_stop_signals`'s result) its handler back."""
    for signum, handler in previous.items():
        signal.signal(signum, handler)
