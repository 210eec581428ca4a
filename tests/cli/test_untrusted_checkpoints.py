"""A checkpoint carrying a ``__reduce__`` payload is refused by every entry point, and the payload never runs.

Entry points: ``unicorn-eval``, ``unicorn-reconstruct``, ``unicorn-train ckpt_path=...`` (resume), and the API
(:func:`unicorn.io.load_model`, :func:`unicorn.io.read_checkpoint`, :func:`unicorn.io.load_reference_checkpoint`).
Released-format files, which hold only tensors and plain data, still load without trusting them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.support.checkpoints import Payload, reference_state
from tests.support.evaluation import tiny_checkpoint, write_inputs
from tests.support.training import TINY
from unicorn.cli import eval as eval_cli
from unicorn.cli import reconstruct as reconstruct_cli
from unicorn.io import UnsafeCheckpointError, load_model, load_reference_checkpoint, read_checkpoint
from unicorn.io.serialization import INTEGRITY_KEY

REPO = Path(__file__).resolve().parents[2]


def released(extra: dict | None = None) -> dict:
    """A released-format checkpoint: what UNICORN's trainer saves (plain dicts, tensors, a Counter, tuples)."""
    state = reference_state()
    adam = {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(2)}}, "param_groups": [{"lr": 1e-4}]}
    return {
        "epoch": 2,
        "batch": 17,
        "model_name": "unicorn",
        "model_kwargs": {"mesh": {"init": "ellipse", "scale": 0.6}, "rend_predictor": {"n_elev_azim": (1, 6)}},
        "model_state": state,
        "optimizer_state": adam,
        "scheduler_state": {"milestones": Counter({800: 1}), "gamma": 0.2, "last_epoch": np.int64(2)},
        **(extra or {}),
    }


@pytest.fixture
def marker(tmp_path: Path) -> Path:
    return tmp_path / "PWNED"


@pytest.fixture
def evil_pkl(tmp_path: Path, marker: Path) -> Path:
    path = tmp_path / "car_big.pkl"
    torch.save(released({"epoch": Payload(marker)}), path)
    return path


@pytest.fixture
def evil_plain(tmp_path: Path, marker: Path) -> Path:
    data = torch.load(tiny_checkpoint(tmp_path / "tiny.pt"), weights_only=True)
    data.pop(INTEGRITY_KEY)  # a hand-made file, as an attacker would write it
    data["info"] = {"epoch": Payload(marker)}
    torch.save(data, tmp_path / "evil.pt")
    return tmp_path / "evil.pt"


def test_api_refuses(evil_pkl: Path, evil_plain: Path, marker: Path) -> None:
    for path in (evil_pkl, evil_plain):
        with pytest.raises(UnsafeCheckpointError, match="--trust-checkpoint"):
            load_model(path)
        with pytest.raises(UnsafeCheckpointError, match="trust=True"):
            read_checkpoint(path)
    with pytest.raises(UnsafeCheckpointError):
        load_reference_checkpoint(evil_pkl)
    assert not marker.exists()
    model = load_reference_checkpoint(evil_pkl, trust=True)  # the caller's explicit choice
    assert marker.exists() and model is not None


def test_released_format_loads_untrusted(tmp_path: Path) -> None:
    torch.save(released(), tmp_path / "model.pkl")
    model, info = load_model(tmp_path / "model.pkl")
    assert info.format == "reference" and info.epoch == 2
    assert load_reference_checkpoint(tmp_path / "model.pkl").config["pose"]["n_azim"] == 6


def test_eval_refuses(evil_pkl: Path, marker: Path, tmp_path: Path, capsys) -> None:
    code = eval_cli.main([str(evil_pkl), "--dataset", "folder", "--root", str(tmp_path), "--out", str(tmp_path / "e")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--trust-checkpoint" in err and str(evil_pkl) in err
    assert not marker.exists() and not (tmp_path / "e").exists()


def test_reconstruct_refuses(evil_plain: Path, marker: Path, tmp_path: Path, capsys) -> None:
    write_inputs(tmp_path / "inputs")
    out = tmp_path / "out"
    code = reconstruct_cli.main([str(evil_plain), str(tmp_path / "inputs"), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("unicorn-reconstruct: error: refusing to load")
    assert not marker.exists() and not out.exists()
    # the flag the message names does what it says (here: the payload runs)
    args = [str(evil_plain), str(tmp_path / "inputs" / "photo.jpg"), "--out", str(out), "--quiet", "--trust-checkpoint"]
    assert reconstruct_cli.main([*args, "--view-size", "32", "--turntable-frames", "0"]) == 0
    assert marker.exists()


def test_train_resume_refuses(synthetic_cache: Path, tmp_path: Path, marker: Path) -> None:
    # a unicorn-train checkpoint (Lightning layout) with the payload among its hyper-parameters
    ckpt = {"epoch": 0, "global_step": 2, "state_dict": {}, "hyper_parameters": {"seed": Payload(marker)}}
    torch.save(ckpt, tmp_path / "evil.ckpt")
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0", "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", *TINY, f"ckpt_path={tmp_path / 'evil.ckpt'}",
         f"hydra.run.dir={run}"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = [line for line in proc.stderr.splitlines() if "error" in line.lower()]
    assert lines == [line for line in lines if line.startswith("unicorn-train: error: refusing to load")], lines
    assert "Traceback" not in proc.stderr and "trust_checkpoint=true" in proc.stderr
    assert not marker.exists()
    assert not run.exists()  # failed before the first iteration: no half-created run folder


def test_corrupted_checkpoint_is_named(tmp_path: Path, capsys) -> None:
    path = tiny_checkpoint(tmp_path / "tiny.pt")
    raw = bytearray(path.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 4096] = bytes(b ^ 0xFF for b in raw[middle : middle + 4096])  # 4 KB of flipped bytes
    path.write_bytes(bytes(raw))
    write_inputs(tmp_path / "inputs")
    code = reconstruct_cli.main([str(path), str(tmp_path / "inputs"), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and f"checkpoint {path}" in err
    assert "corrupted" in err or "cannot read" in err
    assert not (tmp_path / "out").exists()
