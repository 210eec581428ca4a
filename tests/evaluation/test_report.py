"""Metric files and the visual report."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tests.support.evaluation import referenced_files, report_result
from unicorn.evaluation import format_table, write_metrics, write_report
from unicorn.evaluation.pictures import image_grid, mask_overlay


def test_format_table() -> None:
    text = format_table([{"group": "chair", "n-images": 3, "chamfer-L1": 0.123456}], ["chamfer-L1", "mask-iou"])
    lines = text.splitlines()
    assert lines[0].split() == ["group", "n-images", "chamfer-L1", "mask-iou"]
    assert lines[2].split() == ["chair", "3", "0.1235", "-"]
    # angles in degrees with one decimal; colour errors, whatever their names end with, with four
    columns = ["rot-err-mean", "azim-err-median", "color-err-mean", "color-err-mean-overlap"]
    row = {"group": "car", "n-images": 2, **dict(zip(columns, [12.345, 3.21, 0.0756, 0.0612], strict=True))}
    assert format_table([row], columns).splitlines()[2].split() == ["car", "2", "12.3", "3.2", "0.0756", "0.0612"]


def test_metric_files(tmp_path: Path, real_model) -> None:
    result = report_result(real_model)
    paths = write_metrics(result, tmp_path, {"checkpoint": Path("/x/model.pkl")})
    with open(paths["csv"], encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["group", "n-images", "mask-iou", "rec-mse"] and rows[-1]["group"] == "mean"
    data = json.loads(paths["json"].read_text())  # strict JSON: NaN written as null
    assert data["mean"]["mask-iou"] == 0.5 and data["per_image"][1]["mask-iou"] is None
    assert data["better"] == {"mask-iou": "higher", "rec-mse": "lower"} and data["checkpoint"] == "/x/model.pkl"
    # per_image.csv: each row the result's row of that image, cell by cell (NaN as Python writes it, "nan")
    with open(paths["per_image"], encoding="utf-8", newline="") as f:
        reader = csv.DictReader(f)
        images = list(reader)
    assert reader.fieldnames == ["index", "group", "mask-iou", "rec-mse"]
    assert len(images) == len(result.per_image) == 2
    for written, row in zip(images, result.per_image, strict=True):
        assert int(written["index"]) == row["index"] and written["group"] == row["group"]
        for column in ("mask-iou", "rec-mse"):
            value = float(written[column])
            assert (math.isnan(value) and math.isnan(row[column])) or value == row[column], (column, written)
    assert images[1]["mask-iou"] == "nan"


def test_report_page_and_grid(tmp_path: Path, real_model) -> None:
    result = report_result(real_model)
    paths = write_report(real_model, result, tmp_path, "test run", {"dataset": "synthetic"}, view_size=40,
                         turntable_frames=3)  # fmt: skip
    for source in referenced_files(paths["html"]):
        assert (tmp_path / source).is_file() or source.endswith((".csv", ".json")), source
    sources = referenced_files(paths["html"])
    assert sum(s.endswith(".gif") for s in sources) == 2 and "report.png" in sources
    grid = Image.open(paths["png"])
    assert grid.width > 9 * 40 and grid.height > 2 * 40  # 9 pictures per row, 2 rows
    text = paths["html"].read_text()
    assert "mask-iou" in text and "test run" in text and "synthetic" in text


def test_report_captions_list_every_per_image_score(tmp_path: Path, real_model) -> None:
    result = report_result(real_model, n_samples=1)
    result.columns = ["mask-iou", "rot-err-mean", "color-err", "rec-mse"]
    scores = {"candidate": 2, "rec-mse": 0.01, "mask-iou": 0.5, "color-err": 0.0756, "rot-err": 12.345}
    result.samples[0].scores = scores
    page = write_report(real_model, result, tmp_path, "t", {}, view_size=24, turntable_frames=0, interactive=False)
    (caption,) = re.findall(r'<td class="cap">(.*?)</td>', page["html"].read_text(), re.S)
    # the key scores first, then table order, then rot-err (no column of its own); the candidate is no score
    assert caption.splitlines() == [
        "#0 chair", "mask-iou: 0.5000", "rec-mse: 0.0100", "color-err: 0.0756", "rot-err: 12.3",
    ]  # fmt: skip


def test_mask_overlay_and_grid() -> None:
    alpha = torch.tensor([[[1.0, 1.0], [0.0, 0.0]]])
    gt = torch.tensor([[[1.0, 0.0], [1.0, 0.0]]])
    colours = mask_overlay(alpha, gt)
    np.testing.assert_allclose(colours[0, 0], 0.3)  # both: dark
    np.testing.assert_allclose(colours[1, 1], 1.0)  # neither: white
    assert colours[0, 1, 0] > colours[0, 1, 2] and colours[1, 0, 2] > colours[1, 0, 0]  # red = FP, blue = FN
    cell = (torch.rand(8, 8, 3) * 255).to(torch.uint8).numpy()
    grid = image_grid([[cell, cell], [cell]], ["a", "b"], ["row 1", "row 2"])
    assert grid.size[0] > 16 and grid.size[1] > 16


def test_every_metric_column_has_a_direction_and_a_meaning() -> None:
    from unicorn.evaluation.protocols import METRIC_HELP, METRIC_ORDER, METRICS

    assert list(METRIC_ORDER) == [name for name in METRICS if name != "n-images"]
    assert set(METRIC_ORDER.values()) == {"lower", "higher"}
    assert all(METRIC_HELP[name].strip() for name in METRICS)


def test_report_settings_show_names_beyond_ascii_as_written(tmp_path: Path, real_model) -> None:
    """A folder named in UTF-8 reads as written; one whose name is not UTF-8 (its bytes kept as surrogates, as
    Python reads such a file name) does not stop the page from being written."""
    result = report_result(real_model, n_samples=0)
    meta = {"root": "/données/voitures_车", "checkpoint": "/runs/bad\udce9name/model.pkl"}
    page = write_report(real_model, result, tmp_path, "t", meta, interactive=False)["html"]
    text = page.read_text(encoding="utf-8")
    assert "<code>&quot;/données/voitures_车&quot;</code>" in text
    assert "<code>&quot;/runs/bad\\udce9name/model.pkl&quot;</code>" in text
