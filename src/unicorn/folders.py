"""The folders above a file that is about to be written, made with a file in their way named in one line (the
system's own error names the folder it could not make, not why): saves, exports and generated datasets alike."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["make_parent_folders"]


def make_parent_folders(path: str | os.PathLike) -> None:
    """Create the missing folders above the file ``path``.

    Raises:
        NotADirectoryError: one of them is a file (or another non-folder); the message names it, in one line.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):  # the system names the folder it could not make, not why
        above = next((p for p in path.parents if p.exists() or p.is_symlink()), None)
        if above is None or above.is_dir():
            raise
        what = "a file" if above.is_file() else "a broken link" if above.is_symlink() else "not a folder"
        raise NotADirectoryError(f"cannot write {path}: {above} is {what}, where a folder goes") from None
