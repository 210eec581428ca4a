"""The one exception family for mistakes a user can fix (a missing file, a bad option, an unsafe checkpoint).

Command-line entry points report a :class:`UserError` in one line on stderr with exit status 2; anything else is
a bug and keeps its traceback. Library code raises the most specific subclass it has; each subclass also derives
from the built-in exception callers already catch (``ValueError``, ``FileNotFoundError``...).
"""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(Exception):
    """A mistake in the user's input or environment; the message says what is wrong and how to fix it."""
