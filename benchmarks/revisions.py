"""Another git revision of this repository beside the working tree, for benchmarks that compare the two.

``tree_of(REV)`` checks REV out once (a detached ``git worktree`` under the system's temporary folder, reused
by later runs); ``child_env(tree)`` is the environment of a subprocess that imports that tree's ``unicorn``.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BENCHMARKS = Path(__file__).resolve().parent


def tree_of(ref: str) -> Path:
    """A checkout of ``ref`` (a git worktree under the temporary folder, made once)."""
    sha = subprocess.run(["git", "rev-parse", ref], cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()
    path = Path(tempfile.gettempdir()) / f"unicorn-ref-{sha[:12]}"
    if not path.exists():
        cmd = ["git", "worktree", "add", "--detach", str(path), sha]
        subprocess.run(cmd, cwd=REPO, check=True, capture_output=True)
    return path


def child_env(tree: Path, threads: int | None = None) -> dict[str, str]:
    """This process's environment with ``tree``'s sources (and the benchmarks folder) first on the path, before the
    rest of its ``PYTHONPATH`` (dependencies installed into a folder of their own, as gpu_checks.sh does)."""
    env = dict(os.environ)
    rest = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join([str(tree / "src"), str(BENCHMARKS), *rest])
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    return env
