"""The environment of the benchmarks' subprocesses (benchmarks/revisions.py)."""

from __future__ import annotations

import os

from tests.support.benchmarks import load_script, unload_script


def test_child_env_puts_the_tree_first_and_keeps_the_rest_of_the_path(tmp_path, monkeypatch):
    """A tree's sources come first; dependencies installed into a folder of their own on PYTHONPATH (gpu_env.sh's
    kit) stay on it."""
    revisions = load_script("revisions")
    try:
        monkeypatch.setenv("PYTHONPATH", os.pathsep.join(["/kit/site", "/repo/src"]))
        env = revisions.child_env(tmp_path, threads=3)
        assert env["PYTHONPATH"].split(os.pathsep) == [
            str(tmp_path / "src"), str(revisions.BENCHMARKS), "/kit/site", "/repo/src"
        ]  # fmt: skip
        assert env["OMP_NUM_THREADS"] == "3"
        monkeypatch.delenv("PYTHONPATH")
        assert revisions.child_env(tmp_path)["PYTHONPATH"].split(os.pathsep) == [
            str(tmp_path / "src"), str(revisions.BENCHMARKS)
        ]  # fmt: skip
    finally:
        unload_script("revisions")
