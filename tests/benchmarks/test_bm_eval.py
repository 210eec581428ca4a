"""benchmarks/bm_eval.py: a file that holds no model ends the script in one line, before any child starts."""

from __future__ import annotations

import sys

import pytest
import torch

from tests.support.benchmarks import load_script, unload_script


@pytest.fixture(scope="module")
def bm_eval():
    yield load_script("bm_eval")
    unload_script("bm_eval")


@pytest.mark.parametrize(
    "content, message",
    [(b"epoch: 3\n", "it is not a file written by torch.save"), (None, "is not a UNICORN checkpoint")],
)
def test_a_file_that_is_no_checkpoint_stops_before_the_children(bm_eval, tmp_path, monkeypatch, content, message):
    path = tmp_path / "notes.ckpt"
    if content is None:
        torch.save({"weights": torch.ones(2)}, path)  # a torch file, but no model
    else:
        path.write_bytes(content)
    children = []
    monkeypatch.setattr(bm_eval, "run_child", lambda *a, **k: children.append(a))
    monkeypatch.setattr(sys, "argv", ["bm_eval.py", str(path), "--root", str(tmp_path)])
    with pytest.raises(SystemExit) as exit_info:
        bm_eval.main()
    text = str(exit_info.value.code)
    assert text.startswith("bm_eval.py: error: ") and message in text and "\n" not in text
    assert not children
