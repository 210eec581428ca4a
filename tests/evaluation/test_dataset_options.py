"""A run's evaluations read the data it trained on: the dataset options that name it (LSUN's category, a folder's
suffixes) reach :func:`unicorn.evaluation.build_eval_dataset`, ``unicorn-eval`` and the evaluation after training."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from tests.support.datasets import write_lsun
from unicorn.cli.errors import UsageError
from unicorn.cli.eval import _target, build_parser
from unicorn.evaluation import build_eval_dataset


def test_the_lsun_category_a_run_read_is_evaluated(tmp_path: Path) -> None:
    write_lsun(tmp_path, "horse", 6)
    motorbikes = write_lsun(tmp_path, "motorbike", 3)
    # the run's options: the tag and the framing are kept, how training draws (jitter) is not the evaluation's
    data = build_eval_dataset("lsun", str(tmp_path), options={"tag": "motorbike", "cleaned": False, "jitter": 0.0})
    assert data.tag == "motorbike" and data.keys == [*motorbikes, b"ffff_corrupt"]
    assert data.jitter == 0.1 and not data.augment  # the class default: training's draws are not evaluated


def test_a_folder_run_is_evaluated_on_its_suffixes(tmp_path: Path) -> None:
    for name in ("a.png", "b.jpg", "c.png"):
        Image.fromarray(np.full((8, 8, 3), 100, np.uint8)).save(tmp_path / name)
    assert [p.name for p in build_eval_dataset("folder", str(tmp_path)).files] == ["a.png", "b.jpg", "c.png"]
    kept = build_eval_dataset("folder", str(tmp_path), options={"extensions": ["png"]})
    assert [p.name for p in kept.files] == ["a.png", "c.png"]


def _args(*argv: str) -> argparse.Namespace:
    return build_parser().parse_args(["model.ckpt", *argv])


def test_unicorn_eval_takes_the_run_s_lsun_category_or_tag(tmp_path: Path) -> None:
    run = {"name": "lsun", "root": str(tmp_path), "options": {"tag": "motorbike", "cleaned": True, "jitter": 0.0}}
    target = _target(_args(), SimpleNamespace(dataset=run))
    assert target.dataset == "lsun" and target.dataset_options["tag"] == "motorbike"
    assert _target(_args("--tag", "horse"), SimpleNamespace(dataset=run)).dataset_options["tag"] == "horse"
    # a released checkpoint names no dataset: the category must be said
    released = SimpleNamespace(dataset=None)
    assert _target(_args("--dataset", "lsun", "--root", "x", "--tag", "horse"), released).dataset_options == {
        "tag": "horse"
    }
    with pytest.raises(UsageError, match=r"^lsun needs --tag, the LSUN category whose folder is under --root"):
        _target(_args("--dataset", "lsun", "--root", "x"), released)
    with pytest.raises(UsageError, match=r"^--tag is for lsun only \(the LSUN category\), not folder$"):
        _target(_args("--dataset", "folder", "--root", "x", "--tag", "horse"), released)
