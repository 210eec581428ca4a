"""A training run's folder: which checkpoint ``ckpt_path`` names."""

from __future__ import annotations

import pytest

from unicorn.errors import UserError
from unicorn.io.run_folder import resolve_ckpt


def test_ckpt_path_must_be_a_file(tmp_path) -> None:
    with pytest.raises(IsADirectoryError, match=rf"ckpt_path: {tmp_path} is a directory, not a checkpoint file"):
        resolve_ckpt(str(tmp_path), tmp_path / "checkpoints")
    with pytest.raises(FileNotFoundError, match="ckpt_path: no checkpoint file at"):
        resolve_ckpt(str(tmp_path / "missing.ckpt"), tmp_path / "checkpoints")
    with pytest.raises(UserError):
        resolve_ckpt(str(tmp_path), tmp_path / "checkpoints")
    (tmp_path / "a.ckpt").write_bytes(b"x")
    assert resolve_ckpt(str(tmp_path / "a.ckpt"), tmp_path / "checkpoints") == str(tmp_path / "a.ckpt")
    assert resolve_ckpt("last", tmp_path / "checkpoints") is None  # no last.ckpt yet: from scratch
