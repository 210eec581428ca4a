"""benchmarks/bm_metrics.py: each backend's figures, side by side."""

from __future__ import annotations

import re

import pytest

from tests.support.benchmarks import load_script, unload_script


@pytest.fixture(scope="module")
def metrics():
    yield load_script("bm_metrics")
    unload_script("bm_metrics")


def test_backends_side_by_side_give_the_same_scores(metrics, capsys):
    metrics.main(["--device", "cpu", "--points", "300", "--icp-iters", "2", "--backends", "auto,torch"])
    out = capsys.readouterr().out
    for backend in ("auto", "torch"):
        assert f"[{backend}] chamfer-L1 + normal-cos 300 x 300" in out
        assert f"[{backend}] gradient ICP 2 it, 300 pts" in out
    scores = re.findall(r"chamfer-L1=(\S+) normal-cos=(\S+)", out)
    icps = re.findall(r"icp loss=(\S+) scale=(.+)", out)
    assert len(scores) == len(icps) == 2
    assert scores[0] == scores[1] and icps[0] == icps[1]  # the brute force finds the trees' neighbours


def test_unknown_backend_is_an_error(metrics, capsys):
    with pytest.raises(SystemExit) as exit_info:
        metrics.main(["--device", "cpu", "--backends", "auto,faiss"])
    assert exit_info.value.code == 2
    assert "--backends: unknown ['faiss']" in capsys.readouterr().err
