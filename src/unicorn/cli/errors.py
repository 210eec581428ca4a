"""How every command-line tool reports errors: an expected failure in one line, a bug with its traceback.

Expected failures end the command with ``<prog>: error: <message>`` on stderr, on one line, and exit status 2,
as argparse does for a bad option (:func:`expected_error` decides):

- a :class:`unicorn.errors.UserError` (a bad value, a missing or unsafe file, a checkpoint of the wrong kind...);
- an ``OSError``: a missing path, a permission, a read-only or full disk (the message names the path when the
  system gives it);
- Lightning's ``MisconfigurationException`` (e.g. ``trainer.accelerator=gpu`` on a machine without one);
- a DataLoader worker that died (killed for memory) or raised one of the above: the worker's message, not its
  traceback;
- any of these wrapped by Hydra's ``instantiate`` ("Error in call to target ..."): the cause.

The same failures in a background thread (TensorBoard's writer) print one line, ``<prog>: error in thread <name>:
<message>``. Anything else is a bug and keeps its traceback (exit status 1). ``--debug`` (or ``HYDRA_FULL_ERROR=1`` /
``UNICORN_DEBUG=1`` in the environment) shows the traceback of expected failures too.

unicorn's own warnings (:class:`unicorn.errors.UnicornWarning`) are logged in one line (:func:`log_warnings`).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

from unicorn.errors import Interrupted, UnicornWarning, UserError, interrupt_on_signal

__all__ = [
    "USER_ERRORS",
    "ConsoleStream",
    "SweepError",
    "UsageError",
    "add_debug_argument",
    "debug_requested",
    "expected_error",
    "folder_path",
    "log_warnings",
    "one_line",
    "positive_int",
    "report_errors",
    "seed_number",
    "tolerate_closed_stdout",
    "whole_number",
]


class UsageError(UserError, ValueError):
    """Options that do not fit together or do not fit this machine (the message names the option)."""


class SweepError(UsageError):
    """A sweep (``-m``) that cannot run as asked, whichever its job: said once, and the sweep stops."""


#: exceptions reported in one line: the user can fix them (a path, a permission, a full disk, a bad value)
USER_ERRORS: tuple[type[BaseException], ...] = (UserError, OSError)

#: how torch re-raises an exception of a DataLoader worker: its type, the worker, then the worker's traceback
_WORKER = re.compile(r"Caught (\w+) in DataLoader worker process (\d+)\.\s*Original ", re.S)
#: the message of a worker killed from outside (by the kernel for memory, or a signal)
_WORKER_DIED = "DataLoader worker (pid"


def _user_error_names() -> set[str]:
    """Names of the :class:`UserError` classes defined so far (torch re-raises a worker's error as a
    ``RuntimeError`` when it cannot rebuild its type)."""
    names, todo = set(), [UserError]
    while todo:
        cls = todo.pop()
        names.add(cls.__name__)
        todo += cls.__subclasses__()
    return names


def _worker_message(err: BaseException) -> tuple[str, str, str] | None:
    """``(type name, worker, message)`` of an error torch re-raised from a DataLoader worker, else None."""
    text = str(err.args[0]) if err.args else ""
    match = _WORKER.match(text)
    if match is None:
        return None
    name, worker = match.group(1), match.group(2)
    # the traceback ends with "<module>.<Name>: <message>" (after any chained exceptions)
    start = max(text.rfind(f".{name}: "), text.rfind(f"\n{name}: "))
    message = text[start + len(name) + 3 :] if start >= 0 else text.splitlines()[-1]
    return name, worker, message


def _is_misconfiguration(err: BaseException) -> bool:
    """Lightning's error for trainer flags this machine or installation cannot honour."""
    return any(
        cls.__name__ == "MisconfigurationException" and cls.__module__.startswith("lightning")
        for cls in type(err).__mro__
    )


def expected_error(err: BaseException) -> BaseException | None:
    """The error to report in one line if ``err`` is an expected failure (see the module docstring), else None.

    Hydra's instantiation errors are unwrapped to their cause.
    """
    if type(err).__name__ == "InstantiationException" and err.__cause__ is not None:
        return expected_error(err.__cause__)
    if isinstance(err, USER_ERRORS) or _is_misconfiguration(err):
        return err
    worker = _worker_message(err)
    if worker is not None and worker[0] in _user_error_names():
        return err
    if isinstance(err, RuntimeError) and str(err).startswith(_WORKER_DIED):
        return err
    return None


def debug_requested(flag: bool = False) -> bool:
    """``--debug`` given, or ``HYDRA_FULL_ERROR=1`` / ``UNICORN_DEBUG=1`` set."""
    return flag or any(os.environ.get(name, "0") not in ("", "0") for name in ("HYDRA_FULL_ERROR", "UNICORN_DEBUG"))


def one_line(err: BaseException) -> str:
    """The error's message on one line (a ``KeyError``'s message without its quotes; a DataLoader worker's error
    by its message and the worker, without the worker's traceback)."""
    worker = _worker_message(err)
    if worker is not None:
        text: object = f"{worker[2]} (in DataLoader worker {worker[1]})"
    elif isinstance(err, KeyError) and len(err.args) == 1:
        text = err.args[0]
    elif isinstance(err, OSError) and isinstance(err.filename, bytes):  # printed as b'...' otherwise
        paths = [os.fsdecode(name) for name in (err.filename, err.filename2) if name is not None]
        text = f"[Errno {err.errno}] {err.strerror}: {' -> '.join(paths)}"
    else:
        text = err
    return " ".join(str(text).split()) or type(err).__name__


def whole_number(text: str) -> int:
    """An argparse ``type``: a whole number, also written as ``1e6`` (a usage error, exit status 2, otherwise).
    How large it may be is for the command to say (:func:`unicorn.checks.check_limit`)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value.is_integer()):
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}")
    return int(value)


def positive_int(text: str) -> int:
    """An argparse ``type``: a whole number >= 1 (``1e6`` included; a usage error, exit status 2, otherwise)."""
    try:
        value = whole_number(text)
    except argparse.ArgumentTypeError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text!r}")
    return value


def folder_path(text: str) -> Path:
    """An argparse ``type``: a folder path, not empty (an unset shell variable, ``--out "$OUT"``, would otherwise
    name the current folder; a usage error, exit status 2)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"must name a folder, got {text!r}")
    return Path(text)


def seed_number(text: str) -> int:
    """An argparse ``type``: a seed, a whole number in [0, :data:`~unicorn.checks.MAX_SEED`] (numpy's seeds;
    a usage error, exit status 2, otherwise)."""
    from unicorn.checks import MAX_SEED, is_seed

    try:
        value = whole_number(text)
    except argparse.ArgumentTypeError:
        value = -1
    if not is_seed(value):
        raise argparse.ArgumentTypeError(f"must be a whole number in [0, {MAX_SEED}] (numpy's seeds), got {text!r}")
    return value


def add_debug_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--debug`` (tracebacks for user errors too)."""
    parser.add_argument(
        "--debug", action="store_true", help="show the full traceback of errors (also: HYDRA_FULL_ERROR=1)"
    )


#: the logger of unicorn's warnings in the command-line programs (:func:`log_warnings`)
WARNINGS_LOGGER = "unicorn.warnings"


@contextmanager
def log_warnings() -> Iterator[None]:
    """In this block each :class:`~unicorn.errors.UnicornWarning` that the warning filters let through is logged by
    the logger :data:`WARNINGS_LOGGER` at its class's level, in one line (``<Class>: <message>``): on the console
    and, in ``unicorn-train``, into the run's ``train.log``; not printed as Python prints a warning (the file and
    line that warned, then the source line). Other warnings print as before. The filters and the way warnings print
    are back as they were after the block.
    """
    with warnings.catch_warnings():
        shown = warnings.showwarning

        def show(
            message: Warning | str,
            category: type[Warning],
            filename: str,
            lineno: int,
            file: TextIO | None = None,
            line: str | None = None,
        ) -> None:
            if issubclass(category, UnicornWarning):
                logging.getLogger(WARNINGS_LOGGER).log(category.level, "%s: %s", category.__name__, message)
            else:
                shown(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


@contextmanager
def _thread_errors(prog: str, debug: bool) -> Iterator[None]:
    """In this block an expected failure in a background thread (TensorBoard's writer on a full or read-only disk)
    is printed in one line, ``<prog>: error in thread <name>: <message>``, instead of its traceback."""
    previous = threading.excepthook

    def hook(args: threading.ExceptHookArgs) -> None:
        reported = expected_error(args.exc_value) if args.exc_value is not None else None
        if reported is None or debug_requested(debug):
            previous(args)
            return
        name = args.thread.name if args.thread is not None else "?"
        print(f"{prog}: error in thread {name}: {one_line(reported)}", file=sys.stderr)

    threading.excepthook = hook
    try:
        yield
    finally:
        threading.excepthook = previous


class ConsoleStream:
    """A console stream (``sys.stdout``) whose reader may go away (``| head``, a closed terminal): the first write
    that finds the pipe broken points the stream's file descriptor at ``/dev/null`` and the command goes on
    writing there, where a ``BrokenPipeError`` would stop it (a progress bar's) or fill stderr (each log record's).
    Everything else is the wrapped stream's."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._reader_gone()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._reader_gone()

    def _reader_gone(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())  # what the stream still holds is flushed there too, at exit
        os.close(devnull)

    def __getattr__(self, name: str) -> object:
        return getattr(self._stream, name)


def tolerate_closed_stdout() -> None:
    """Wrap ``sys.stdout`` in a :class:`ConsoleStream` (once), before anything keeps a reference to it."""
    if not isinstance(sys.stdout, ConsoleStream) and hasattr(sys.stdout, "fileno"):
        try:
            sys.stdout.fileno()
        except (OSError, ValueError):  # not a file (a test's capture): nothing to point elsewhere
            return
        sys.stdout = ConsoleStream(sys.stdout)  # type: ignore[assignment]


def report_errors(
    prog: str,
    func: Callable[[], int],
    debug: bool = False,
    cleanup: Callable[[], None] | None = None,
) -> int:
    """Run ``func``; an expected failure (:func:`expected_error`, the same for every command) is printed as
    ``<prog>: error: <message>`` and gives exit status 2.

    SIGTERM and SIGINT stop the command at once (:func:`unicorn.errors.interrupt_on_signal`): ``<prog>: stopped by
    SIGTERM``, exit status ``128 + signal``, after ``cleanup``. Any other exception (a bug) propagates with its
    traceback (exit status 1), after ``cleanup``. unicorn's warnings are logged in one line (:func:`log_warnings`).

    Args:
        prog: the command's name.
        func: the command; returns its exit status.
        debug: re-raise user errors (traceback) instead.
        cleanup: called before reporting any error (e.g. to remove a half-created output folder).
    """
    tolerate_closed_stdout()
    try:
        with interrupt_on_signal(), log_warnings(), _thread_errors(prog, debug):
            return func()
    except Interrupted as err:
        if cleanup is not None:
            cleanup()
        print(f"{prog}: {one_line(err)}", file=sys.stderr)
        return err.exit_status
    except Exception as err:
        if cleanup is not None:
            cleanup()
        reported = expected_error(err)
        if reported is None or debug_requested(debug):
            raise
        print(f"{prog}: error: {one_line(reported)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if cleanup is not None:
            cleanup()
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
