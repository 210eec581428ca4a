"""The metric loggers' files: kept across resumes, rewritten whole or not at all."""

from __future__ import annotations

import csv

import pytest

from unicorn.lit.loggers import CSVLogger, log_step


def _rows(path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
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
    with open(path, newline="") as f:
        lines = list(csv.reader(f))
    assert all(len(line) == len(lines[0]) for line in lines)
    assert [(r["step"], r["train/loss"]) for r in _rows(path)] == [(str(s), f"{s + 0.25}") for s in range(5)]


def test_log_step_puts_an_iterations_evaluation_beside_its_training_values() -> None:
    assert [log_step(n) for n in (0, 1, 2, 600)] == [0, 0, 1, 599]
