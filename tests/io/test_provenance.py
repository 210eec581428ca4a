"""The checkout state recorded in every provenance record (:func:`unicorn.io.provenance.checkout_state`)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from unicorn.io.provenance import checkout_state, command_line

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(root: Path, *args: str) -> str:
    cmd = ["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@example.org", *args]
    return subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip()


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    root.mkdir()
    _git(root, "init", "-q")
    (root / "a.py").write_text("x = 1\n")
    _git(root, "add", "a.py")
    _git(root, "commit", "-q", "-m", "one")
    return root


def test_a_clean_checkout_is_its_commit(checkout: Path) -> None:
    (checkout / "untracked.txt").write_text("not part of the code\n")
    assert checkout_state(checkout) == _git(checkout, "rev-parse", "HEAD")


def test_edits_are_told_apart_by_their_digest(checkout: Path) -> None:
    commit = _git(checkout, "rev-parse", "HEAD")
    (checkout / "a.py").write_text("x = 2\n")
    first = checkout_state(checkout)
    assert first is not None and first.startswith(f"{commit}+dirty.") and len(first) == len(commit) + 7 + 12
    assert checkout_state(checkout) == first  # a function of the edits
    (checkout / "a.py").write_text("x = 3\n")
    second = checkout_state(checkout)
    assert second is not None and second.startswith(f"{commit}+dirty.") and second != first
    _git(checkout, "add", "a.py")  # staged edits are edits too
    assert checkout_state(checkout) == second
    (checkout / "a.py").write_text("x = 1\n")
    _git(checkout, "add", "a.py")
    assert checkout_state(checkout) == commit


def test_no_checkout_is_none(tmp_path: Path) -> None:
    assert checkout_state(tmp_path) is None


def test_command_line_quotes_what_the_shell_would_split() -> None:
    line = command_line("unicorn-train", ["seed=1", "hydra.run.dir=my runs"])
    assert line == "unicorn-train seed=1 'hydra.run.dir=my runs'"
