"""How every command-line tool reports errors: a user's mistake in one line, a bug with its traceback.

A :class:`unicorn.errors.UserError` (and the few built-in errors that always mean a wrong path or option:
``FileNotFoundError``, ``NotADirectoryError``, ``IsADirectoryError``, ``PermissionError``) ends the command with
``<prog>: error: <message>`` on stderr, on one line, and exit status 2, as argparse does for a bad option.
Anything else is a bug and keeps its traceback. ``--debug`` (or ``HYDRA_FULL_ERROR=1`` / ``UNICORN_DEBUG=1`` in
the environment) shows the traceback of user errors too.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

from unicorn.errors import UserError

__all__ = ["USER_ERRORS", "UsageError", "add_debug_argument", "debug_requested", "one_line", "report_errors"]


class UsageError(UserError, ValueError):
    """Options that do not fit together or do not fit this machine (the message names the option)."""


#: exceptions reported in one line: the user can fix them
USER_ERRORS: tuple[type[BaseException], ...] = (
    UserError,
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
)


def debug_requested(flag: bool = False) -> bool:
    """``--debug`` given, or ``HYDRA_FULL_ERROR=1`` / ``UNICORN_DEBUG=1`` set."""
    return flag or any(os.environ.get(name, "0") not in ("", "0") for name in ("HYDRA_FULL_ERROR", "UNICORN_DEBUG"))


def one_line(err: BaseException) -> str:
    """The error's message on one line (a ``KeyError``'s message without its quotes)."""
    text = err.args[0] if isinstance(err, KeyError) and len(err.args) == 1 else err
    return " ".join(str(text).split()) or type(err).__name__


def add_debug_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--debug`` (tracebacks for user errors too)."""
    parser.add_argument(
        "--debug", action="store_true", help="show the full traceback of errors (also: HYDRA_FULL_ERROR=1)"
    )


def report_errors(
    prog: str,
    func: Callable[[], int],
    debug: bool = False,
    extra: tuple[type[BaseException], ...] = (),
    cleanup: Callable[[], None] | None = None,
) -> int:
    """Run ``func``; a user error is printed as ``<prog>: error: <message>`` and gives exit status 2.

    Args:
        prog: the command's name.
        func: the command; returns its exit status.
        debug: re-raise user errors (traceback) instead.
        extra: more exception types this command reports as user errors.
        cleanup: called before reporting a user error (e.g. to remove a half-created output folder).
    """
    try:
        return func()
    except USER_ERRORS + extra as err:
        if cleanup is not None:
            cleanup()
        if debug_requested(debug):
            raise
        print(f"{prog}: error: {one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if cleanup is not None:
            cleanup()
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
