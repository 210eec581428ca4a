"""Commands run as new processes forked from a server that imported torch, Lightning and unicorn's CLI once.

A fresh ``python -m unicorn.cli.train`` spends most of a refused or a tiny run importing torch and Lightning. A
fork of a server that has them imported is still a new process: its own exit status, stdout and stderr, working
directory, environment and thread count, with ``main()`` running as the console script runs it. The server is a
clean interpreter (multiprocessing's fork server), never the test process, whose threads may hold locks. Tests of
what only a new interpreter shows (``python -m``, ``--help``, DDP's re-launch, signals) start one with
:mod:`subprocess` instead.
"""

from __future__ import annotations

import importlib
import multiprocessing
import multiprocessing.context
import os
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["PRELOAD", "context", "run_command"]

#: the modules the server imports once; a command importing more imports them itself
PRELOAD = ["torch", "lightning", "unicorn.cli.train", "unicorn.config.schema", "unicorn.lit.run"]


def context() -> multiprocessing.context.BaseContext:
    """The fork server's context (one server per test process, started at its first command)."""
    forkserver = multiprocessing.get_context("forkserver")
    forkserver.set_forkserver_preload(PRELOAD)
    return forkserver


def _command(entry: str, argv: list[str], cwd: str, env: dict[str, str], out: str, err: str) -> None:
    """The forked process: the environment, threads, streams and directory of ``argv``, then ``entry()``."""
    os.environ.clear()
    os.environ.update(env)
    import torch

    if "OMP_NUM_THREADS" in env:  # read once when torch started, in the server: apply the command's own
        torch.set_num_threads(int(env["OMP_NUM_THREADS"]))
    for fd, path in ((1, out), (2, err)):  # the file descriptors, so that every writer's output is caught
        target = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(target, fd)
        os.close(target)
    os.chdir(cwd)
    sys.argv = argv
    module, name = entry.split(":")
    getattr(importlib.import_module(module), name)()  # SystemExit(code) becomes the exit status


def run_command(
    entry: str, argv: list[str], *, cwd: Path, env: dict[str, str], timeout: float
) -> subprocess.CompletedProcess:
    """Run ``entry`` (``"module:function"``, a console script's target) with ``sys.argv = argv`` in a new process.

    Returns what :func:`subprocess.run` with ``capture_output=True, text=True`` returns; raises
    :class:`subprocess.TimeoutExpired` (after killing the process) when it runs longer than ``timeout`` seconds.
    """
    with tempfile.TemporaryDirectory(prefix="unicorn-command-") as tmp:
        out, err = os.path.join(tmp, "stdout"), os.path.join(tmp, "stderr")
        process = context().Process(target=_command, args=(entry, list(argv), str(cwd), dict(env), out, err))
        process.start()
        process.join(timeout)
        if process.exitcode is None:
            process.kill()
            process.join()
            raise subprocess.TimeoutExpired(argv, timeout)
        read = {
            path: Path(path).read_text(encoding="utf-8", errors="replace") if os.path.exists(path) else ""
            for path in (out, err)
        }
        return subprocess.CompletedProcess(argv, process.exitcode, read[out], read[err])
