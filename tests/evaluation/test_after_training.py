"""The evaluation after training on a dataset with unreadable images: as the dataset's ``on_error`` says."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from tests.support.training import TINY, unicorn_train

#: TINY's run, on a folder of images, with a quick evaluation after it
FOLDER_RUN = [
    *(o for o in TINY if not o.startswith(("dataset.", "evaluate.", "trainer.max_steps="))),
    "dataset=folder",
    "dataset.categories=null",  # the experiment's synthetic category: a folder has none
    "dataset.batch_size=4",
    "dataset.cache_items=false",  # the folder's items are augmented
    "trainer.max_steps=2",
    "evaluate.enabled=true",
    "evaluate.num_points=300",
    "evaluate.icp_iterations=2",
    "evaluate.report_samples=0",
    "evaluate.mean_shape_iterations=5",  # a folder serves neither baseline: both left out, named in the log
    "evaluate.own_mean_shape=true",
    "evaluate.shape_points=0",
]


def test_the_evaluation_after_training_skips_unreadable_images_as_training_did(tmp_path: Path) -> None:
    """The folder preset skips unreadable images (``on_error: skip``): training and the evaluation after it leave
    the bad one out, each with a one-line warning in train.log, and every readable image is scored once."""
    folder = tmp_path / "fold"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(8):
        Image.fromarray(rng.integers(0, 256, (40, 48, 3), dtype=np.uint8)).save(folder / f"img{i:02d}.png")
    (folder / "bad.jpg").write_bytes(b"junk" * 10)
    run = tmp_path / "run"
    result = unicorn_train(*FOLDER_RUN, f"dataset.root={folder}", f"hydra.run.dir={run}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert sorted(row["index"] for row in metrics["per_image"]) == list(range(1, 9))  # bad.jpg is item 0
    assert metrics["on_error"] == "skip" and metrics["command"].endswith(" --skip-bad")  # unicorn-eval's equivalent
    log = (run / "train.log").read_text()
    skipped = [line for line in log.splitlines() if "bad.jpg" in line]
    assert skipped and all(
        line.endswith(f"SkippedFileWarning: skipping unreadable file: cannot read image {folder / 'bad.jpg'}: "
                      f"UnidentifiedImageError: cannot identify image file '{folder / 'bad.jpg'}'")
        for line in skipped
    )  # fmt: skip
    assert "RuntimeWarning" not in log + result.stderr and "warnings.warn" not in result.stderr
    for left_out in (
        "evaluate.mean_shape_iterations left out: folder has no training point clouds for a mean shape",
        "evaluate.own_mean_shape left out: folder has no ground-truth point clouds to score the model's own average",
    ):
        assert left_out in log
    assert "--mean-shape=0 " in metrics["command"] and "--own-mean-shape" not in metrics["command"]


def test_a_folder_run_is_evaluated_and_resumed_on_the_suffixes_it_trained_on(tmp_path: Path) -> None:
    """``dataset.options.extensions`` names the run's data: the evaluation after training reads the same images, and
    a resume that would read others is refused."""
    folder = tmp_path / "fold"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(6):
        image = Image.fromarray(rng.integers(0, 256, (40, 48, 3), dtype=np.uint8))
        image.save(folder / f"img{i:02d}.{'png' if i < 4 else 'jpg'}")
    run = tmp_path / "run"
    args = [*FOLDER_RUN, f"dataset.root={folder}", f"hydra.run.dir={run}", "+dataset.options.extensions=[png]"]
    result = unicorn_train(*args, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert sorted(row["index"] for row in metrics["per_image"]) == [0, 1, 2, 3]  # the four PNGs
    resumed = unicorn_train(*args[:-1], "+dataset.options.extensions=[jpg]", "ckpt_path=last", cwd=tmp_path)
    assert resumed.returncode != 0
    assert "dataset.options.extensions ['png'] -> ['jpg']" in resumed.stderr, resumed.stderr[-2000:]
