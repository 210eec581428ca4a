"""The metric loggers' files: kept across resumes, rewritten whole or not at all."""

from __future__ import annotations

import csv

import pytest
import torch

from unicorn.lit.loggers import CSVLogger, log_step


def _rows(path) -> list[dict[str, str]]:
    with open(path, encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))


def test_a_new_column_that_fails_to_write_leaves_the_log_as_it_was(tmp_path, monkeypatch) -> None:
    logger = CSVLogger(str(tmp_path), name="csv", version="")
    for step in range(100):
        logger.log_metrics({"train/loss": float(step)}, step=step)
    path = tmp_path / "csv" / "metrics.csv"
    before = path.read_bytes()
    assert len(_rows(path)) == 100

    def full_disk(self, rows):  # the disk fills while the rows are written again under the new header
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(csv.DictWriter, "writerows", full_disk)
    with pytest.raises(OSError, match="No space left"):
        logger.log_metrics({"heldout/iou": 0.5}, step=100)  # a new column: the file is written anew
    assert path.read_bytes() == before  # Lightning's own rewrite truncated it to the header
    assert [p.name for p in path.parent.iterdir()] == ["metrics.csv"]  # no temporary file left


def test_a_rewrite_writes_a_hidden_temporary_that_a_later_start_removes(tmp_path, monkeypatch) -> None:
    import os
    import subprocess
    import sys

    from omegaconf import OmegaConf

    from unicorn.io.run_folder import plan_folder
    from unicorn.lit.run import write_run_folder

    logger = CSVLogger(str(tmp_path), name="csv", version="")
    logger.log_metrics({"train/loss": 1.0}, step=0)
    seen, writerows = [], csv.DictWriter.writerows
    monkeypatch.setattr(
        csv.DictWriter,
        "writerows",
        lambda self, rows: (seen.extend(os.listdir(tmp_path / "csv")), writerows(self, rows)),
    )
    logger.log_metrics({"heldout/iou": 0.5}, step=1)  # a new column: the file is written anew beside it
    assert sorted(set(seen)) == [f".metrics.csv.tmp-{os.getpid()}", "metrics.csv"]
    # what a SIGKILL during that rewrite, or during heldout.csv's, leaves: a temporary of a process now gone
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True).stdout)
    left = [tmp_path / "csv" / f".metrics.csv.tmp-{dead}", tmp_path / f".heldout.csv.tmp-{dead}"]
    for path in left:
        path.write_text("step,heldout/iou\n0,0.")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"x")
    unhidden = tmp_path / "csv" / f"metrics.csv.tmp-{dead}"  # as unicorn 0.1.0 named it
    unhidden.write_text("step\n")
    assert plan_folder(tmp_path, None, None, overwrite=True)  # replaceable: the run's own kinds of file
    users = tmp_path / f".notes.txt.tmp-{dead}"  # the run folder may be the user's (hydra.run.dir=.)
    users.write_text("mine")
    monkeypatch.chdir(tmp_path)
    write_run_folder(OmegaConf.create({"dataset": {"root": None}}), tmp_path, None, [])
    assert not any(path.exists() for path in left) and users.read_text() == "mine"


def test_dropping_rows_keeps_the_others_and_the_columns(tmp_path) -> None:
    logger = CSVLogger(str(tmp_path), name="csv", version="")
    for step in range(6):
        logger.log_metrics({"train/loss": float(step)}, step=step)
    logger.log_metrics({"heldout/iou": 0.5}, step=log_step(3))  # an evaluation after iteration 3
    assert logger.experiment.drop_from(3) == 3  # the resumed iteration 4 logs at step 3
    rows = _rows(tmp_path / "csv" / "metrics.csv")
    assert [(r["step"], r["train/loss"], r["heldout/iou"]) for r in rows] == [
        ("0", "0.0", ""),
        ("1", "1.0", ""),
        ("2", "2.0", ""),
        ("2", "", "0.5"),
    ]


def test_a_last_row_cut_short_is_dropped_before_rows_are_appended(tmp_path, caplog) -> None:
    logger = CSVLogger(str(tmp_path), name="csv", version="")
    for step in range(4):
        logger.log_metrics({"train/loss": float(step) + 0.25, "train/iou": 0.5}, step=step)
    path = tmp_path / "csv" / "metrics.csv"
    path.write_bytes(path.read_bytes()[:-6])  # a run killed while writing its last row
    resumed = CSVLogger(str(tmp_path), name="csv", version="")
    with caplog.at_level("WARNING", logger="unicorn.lit.loggers"):
        assert resumed.experiment.drop_from(3) == 0  # the cut row of step 3 is not counted as a logged one
    assert "dropped 1 row(s) cut short" in caplog.text
    resumed.log_metrics({"train/loss": 3.25, "train/iou": 0.5}, step=3)
    resumed.log_metrics({"train/loss": 4.25, "train/iou": 0.5}, step=4)
    with open(path, encoding="utf-8", newline="") as f:
        lines = list(csv.reader(f))
    assert all(len(line) == len(lines[0]) for line in lines)
    assert [(r["step"], r["train/loss"]) for r in _rows(path)] == [(str(s), f"{s + 0.25}") for s in range(5)]


def test_log_step_puts_an_iterations_evaluation_beside_its_training_values() -> None:
    assert [log_step(n) for n in (0, 1, 2, 600)] == [0, 0, 1, 599]


def _scalars(folder) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_tensorboard_events_go_on_in_a_new_file_when_the_folder_is_deleted(tmp_path, caplog) -> None:
    import shutil

    from unicorn.lit.loggers import TensorBoardLogger

    logger = TensorBoardLogger(str(tmp_path), name="tensorboard", version="")
    logger.log_metrics({"train/loss": 1.0}, step=0)
    shutil.rmtree(logger.log_dir)  # a clean-up while the run goes on
    with caplog.at_level("WARNING", logger="unicorn.lit.loggers"):
        logger.log_metrics({"train/loss": 2.0}, step=1)
        logger.log_image("images/overview", torch.zeros(3, 4, 4), 1)
        logger.finalize("success")
    assert logger.failure is None and "cannot be written" not in caplog.text
    assert _scalars(logger.log_dir) == {"train/loss": [(1, 2.0)]}


def test_tensorboard_logging_stops_and_training_goes_on_when_events_cannot_be_written(
    tmp_path, monkeypatch, caplog
) -> None:
    from torch.utils.tensorboard import SummaryWriter

    from unicorn.lit.loggers import TensorBoardLogger

    def full_disk(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    logger = TensorBoardLogger(str(tmp_path), name="tensorboard", version="")
    logger.log_metrics({"train/loss": 1.0}, step=0)
    monkeypatch.setattr(SummaryWriter, "add_scalar", full_disk)
    monkeypatch.setattr(SummaryWriter, "add_image", full_disk)
    with caplog.at_level("WARNING", logger="unicorn.lit.loggers"):
        logger.log_metrics({"train/loss": 2.0}, step=1)  # no error: tried again, then given up
        logger.log_image("images/overview", torch.zeros(3, 4, 4), 1)
        logger.log_metrics({"train/loss": 3.0}, step=2)
        logger.finalize("success")
    assert isinstance(logger.failure, OSError) and logger.failure.errno == 28
    assert caplog.text.count("TensorBoard logging stops here, training goes on") == 1
    monkeypatch.undo()
    assert _scalars(logger.log_dir) == {"train/loss": [(0, 1.0)]}


def test_tensorboard_errors_other_than_io_are_raised(tmp_path) -> None:
    from unicorn.lit.loggers import TensorBoardLogger

    logger = TensorBoardLogger(str(tmp_path), name="tensorboard", version="")
    with pytest.raises(ValueError, match="you tried to log"):
        logger.log_metrics({"train/loss": "not a number"}, step=0)
    assert logger.failure is None


def test_rows_appended_to_a_log_follow_its_own_column_order(tmp_path) -> None:
    """A ``metrics.csv`` whose header is not in sorted order (written by another writer): the rows a resumed run
    appends go under the columns that name them, and a new column rewrites the file keeping every value."""
    path = tmp_path / "csv" / "metrics.csv"
    path.parent.mkdir()
    path.write_text("step,train/loss,epoch\n0,1.5,0\n", encoding="utf-8")
    logger = CSVLogger(str(tmp_path), name="csv", version="")
    logger.log_metrics({"train/loss": 2.5, "epoch": 0}, step=1)
    assert path.read_text(encoding="utf-8").splitlines()[0] == "step,train/loss,epoch"  # appended, not rewritten
    assert [(r["step"], r["train/loss"], r["epoch"]) for r in _rows(path)] == [("0", "1.5", "0"), ("1", "2.5", "0")]
    logger.log_metrics({"train/loss": 3.5, "epoch": 0, "heldout/iou": 0.5}, step=2)  # a new column
    assert [(r["step"], r["train/loss"], r["heldout/iou"]) for r in _rows(path)] == [
        ("0", "1.5", ""),
        ("1", "2.5", ""),
        ("2", "3.5", "0.5"),
    ]
