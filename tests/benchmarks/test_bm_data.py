"""benchmarks/bm_data.py: the generated datasets load, and every loader and worker count gets its line."""

from __future__ import annotations

import re

import pytest

from tests.support.benchmarks import load_script, unload_script
from unicorn.data.cub import CUB200
from unicorn.data.folder import ImageFolder


@pytest.fixture(scope="module")
def bm_data():
    yield load_script("bm_data")
    unload_script("bm_data")


def test_generated_data_is_read_by_the_loaders(bm_data, tmp_path):
    roots = bm_data.write_datasets(tmp_path, 6, (90, 70))
    cub = CUB200(roots["cub_200"], "train", img_size=32)
    assert len(cub) == 6 and cub[0]["keypoints"].shape == (15, 3) and 0 < cub[0]["mask"].mean() < 1
    assert len(CUB200(roots["cub_200"], "val")) == 5
    assert len(ImageFolder(roots["folder"])) == 6


def test_one_line_per_loader_and_worker_count(bm_data, tmp_path, capsys):
    args = ["--root", str(tmp_path), "--images", "6", "--source-size", "90x70", "--img-size", "32"]
    bm_data.main([*args, "--workers", "0,1", "--batch-size", "4", "--batches", "2", "--warmup", "1"])
    out = capsys.readouterr().out
    assert "a GPU step consumes 32 images per 0.02 s = 1600 images/s" in out
    rows = re.findall(r"^(folder|cub_200) +(\d+) +\d+ +\d+ +(?:\d+|-) +\d+$", out, flags=re.M)
    assert rows == [("folder", "0"), ("folder", "1"), ("cub_200", "0"), ("cub_200", "1")]


def test_unknown_loader_is_an_error(bm_data, capsys):
    with pytest.raises(SystemExit):
        bm_data.main(["--loaders", "folder,imagenet"])
    assert "--loaders: unknown ['imagenet']" in capsys.readouterr().err
