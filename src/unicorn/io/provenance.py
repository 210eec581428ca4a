"""Where a result came from: the command, the checkpoint, the package version and the git commit.

Every report and metrics file that unicorn writes carries :func:`provenance`'s record, so that a number can be
traced back to the exact command and code that produced it.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import shlex
import subprocess
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from unicorn.errors import UserError
from unicorn.io.run_folder import folder_setting

__all__ = ["ProvenanceError", "checkout_state", "command_line", "git_commit", "provenance", "read_run_starts"]


class ProvenanceError(UserError, ValueError):
    """A run folder's ``provenance.json`` that is not the list of the run's starts (truncated, edited by hand)."""


def read_run_starts(path: Path) -> list[Any]:
    """The records of a run folder's ``provenance.json``, one per start of the run; [] when there is none.

    Raises:
        ProvenanceError: the file is not a JSON list (the message names it and says what to do).
    """
    if not path.exists():
        return []
    try:
        starts = json.loads(path.read_text(encoding="utf-8"))
        reason = "" if isinstance(starts, list) else f"a JSON {type(starts).__name__}"
    except (ValueError, OSError) as err:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        reason = str(err)
    if reason:
        raise ProvenanceError(
            f"{path} is not the list of this run's starts ({reason}); repair it or move it away to train in "
            f"this folder, or train elsewhere ({folder_setting()}=...)"
        )
    return starts


def command_line(prog: str, argv: Sequence[str]) -> str:
    """A shell-quoted command line that reruns ``prog`` with ``argv``."""
    return shlex.join([prog, *argv])


@lru_cache(maxsize=1)
def git_commit() -> str | None:
    """The commit of the git checkout unicorn runs from (:func:`checkout_state`); None for an installed wheel.

    Installed wheels have no checkout: None. Editable installs and source trees report their commit.
    """
    return checkout_state(Path(__file__).resolve().parents[3])  # src/unicorn/io/provenance.py -> the repository


def checkout_state(root: str | os.PathLike) -> str | None:
    """The state of the git checkout at ``root``: its commit, ``<commit>+dirty.<digest>`` when tracked files differ
    from it, the digest (12 hex digits) a hash of those differences, so that two checkouts with other edits never
    look the same; None where ``root`` is not a checkout or git cannot be run.
    """
    root = Path(root)
    if not (root / ".git").exists():
        return None

    def git(*args: str) -> bytes:
        return subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, timeout=10, check=True
        ).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD").decode()
        changes = git("diff", "HEAD", "--binary", "--no-ext-diff", "--no-textconv", "--no-color")
    except (OSError, subprocess.SubprocessError, UnicodeDecodeError):
        return None
    return f"{commit}+dirty.{hashlib.sha256(changes).hexdigest()[:12]}" if changes else commit


def provenance(command: str, checkpoint: str | os.PathLike | None = None, **extra: Any) -> dict[str, Any]:
    """The record written into reports and metrics files.

    Args:
        command: the command line that produced the file (:func:`command_line`).
        checkpoint: the checkpoint it used, stored as an absolute path.
        extra: more entries (e.g. ``produced_by`` for an evaluation run by another command).

    Returns:
        ``{"command", "checkpoint", "unicorn_version", "git_commit", "torch", "created", **extra}``.
    """
    import torch

    from unicorn import __version__

    return {
        "command": command,
        "checkpoint": None if checkpoint is None else str(Path(checkpoint).expanduser().resolve()),
        "unicorn_version": __version__,
        "git_commit": git_commit(),
        "torch": torch.__version__,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        **extra,
    }
