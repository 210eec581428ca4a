"""The argument checks of the scripts in ``benchmarks/`` and ``experiments/``: a bad value ends a script before any
work with argparse's one-line error (``<prog>: error: argument --flag: must be ..., got '...'``, exit status 2).

Each function but :func:`require_cuda` is an argparse ``type`` (or makes one). Whole numbers are read as
:func:`unicorn.cli.errors.whole_number` reads them (``1e6`` too) and worded as its ``positive_int``; this module
imports nothing of ``unicorn`` because the benchmarks' ``--ref`` children import it beside an earlier tree's
``unicorn``, which may lack those.
"""

from __future__ import annotations

import argparse
import math
import subprocess
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

REPO = Path(__file__).resolve().parent.parent


def _number(text: str, kind: type) -> float:
    """``text`` as a finite number (a whole one for ``kind=int``), else NaN."""
    try:
        value = float(text)
    except ValueError:
        return math.nan
    if not math.isfinite(value) or (kind is int and not value.is_integer()):
        return math.nan
    return value


def at_least(minimum: int) -> Callable[[str], int]:
    """A whole number >= ``minimum``."""

    def parse(text: str) -> int:
        value = _number(text, int)
        if not value >= minimum:  # NaN too
            raise argparse.ArgumentTypeError(f"must be a whole number >= {minimum}, got {text!r}")
        return int(text) if text.strip().lstrip("+-").isdigit() else int(value)  # exact for large ones

    return parse


positive_int = at_least(1)
non_negative_int = at_least(0)


def seed_number(text: str) -> int:
    """A seed: a whole number in [0, 2**32 - 1] (numpy's seeds)."""
    value = _number(text, int)
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be a whole number in [0, {2**32 - 1}] (numpy's seeds), got {text!r}")
    return int(value)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _number(text, float)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    value = _number(text, float)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}")
    return value


def power_of_two(text: str) -> int:
    """A whole number 2, 4, 8, ..."""
    value = _number(text, int)
    if not (value >= 2 and math.log2(value).is_integer()):
        raise argparse.ArgumentTypeError(f"must be a power of 2 >= 2, got {text!r}")
    return int(value)


def comma_list(item: Callable[[str], T]) -> Callable[[str], list[T]]:
    """Comma-separated values, each checked by ``item`` (its message names the bad one)."""

    def parse(text: str) -> list[T]:
        return [item(part.strip()) for part in text.split(",")]

    return parse


def names(choices: Iterable[str]) -> Callable[[str], list[str]]:
    """Comma-separated names, each among ``choices``."""
    known = list(choices)

    def parse(text: str) -> list[str]:
        values = [part.strip() for part in text.split(",")]
        if unknown := [v for v in values if v not in known]:
            raise argparse.ArgumentTypeError(f"unknown {unknown}; known: {', '.join(known)}")
        return values

    return parse


def row_numbers(count: int) -> Callable[[str], list[int] | str]:
    """``all``, or comma-separated row numbers in [0, ``count``)."""

    def parse(text: str) -> list[int] | str:
        if text == "all":
            return text
        values = [_number(part, int) for part in text.split(",")]
        if not all(0 <= v < count for v in values):
            raise argparse.ArgumentTypeError(
                f"must be 'all' or comma-separated row numbers from 0 to {count - 1}, got {text!r}"
            )
        return [int(v) for v in values]

    return parse


def existing_file(text: str) -> str:
    """The path of a file that exists."""
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"no such file: {text!r}")
    return text


def existing_folder(text: str) -> str:
    """The path of a folder that exists."""
    if not Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"no such folder: {text!r}")
    return text


def add_checkpoints_and_root(parser: argparse.ArgumentParser) -> None:
    """The positional trained checkpoints and ``--root`` of the scripts that read runs on their synthetic data."""
    parser.add_argument("checkpoints", type=existing_file, nargs="+")
    parser.add_argument(
        "--root",
        type=existing_folder,
        default=None,
        help="the dataset folder (default: each run's own synthetic dataset)",
    )


def git_revision(text: str) -> str:
    """A git revision of this repository that names a commit (``git rev-parse --verify``)."""
    cmd = ["git", "rev-parse", "--verify", "--quiet", f"{text}^{{commit}}"]
    try:
        known = subprocess.run(cmd, cwd=REPO, capture_output=True).returncode == 0
    except OSError as err:  # no git
        raise argparse.ArgumentTypeError(f"cannot run git to check {text!r}: {err}") from None
    if not known or text.startswith("-"):
        raise argparse.ArgumentTypeError(f"not a commit of this repository: {text!r}")
    return text


def require_cuda(parser: argparse.ArgumentParser, device: str) -> None:
    """``--device cuda`` on a machine without CUDA ends the script with a usage error."""
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            parser.error("--device cuda but CUDA is not available")
