"""The one exception family for mistakes a user can fix (a missing file, a bad option, an unsafe checkpoint).

Command-line entry points report a :class:`UserError` in one line on stderr with exit status 2; anything else is
a bug and keeps its traceback. Library code raises the most specific subclass it has; each subclass also derives
from the built-in exception callers already catch (``ValueError``, ``FileNotFoundError``...).
"""

from __future__ import annotations

__all__ = ["Interrupted", "UserError"]


class UserError(Exception):
    """A mistake in the user's input or environment; the message says what is wrong and how to fix it."""


class Interrupted(Exception):
    """A command stopped early by a signal (SIGTERM, SIGINT) after saving what it needs to go on.

    Command-line entry points print the message on one line and exit with :attr:`exit_status` (``128 + signal``,
    as a shell reports a process killed by that signal), not 0: a scheduler sees that the job did not finish.
    """

    def __init__(self, message: str, exit_status: int) -> None:
        super().__init__(message)
        self.exit_status = exit_status
