"""An evaluation's metric files: the text table, ``metrics.csv``, ``per_image.csv`` and ``metrics.json``."""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from unicorn.evaluation.protocols import METRIC_ORDER, ROW_INFO, EvaluationResult

__all__ = ["format_table", "format_value", "json_safe", "write_metrics"]


# ---------------------------------------------------------------------------------------------- tables
def format_value(value: Any, column: str = "") -> str:
    """A table cell: ``-`` for NaN, one decimal for degrees and large values, else four."""
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if column.startswith(("rot-err", "azim-err")) or abs(value) >= 100:
            return f"{value:.1f}"  # degrees (not color-err-mean, a colour error)
        return f"{value:.4f}"
    return str(value)


def format_table(table: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    """A fixed-width text table: one line per row, ``group`` and ``n-images`` first."""
    header = ["group", "n-images", *columns]
    cells = [header] + [[format_value(row.get(c, float("nan")), c) for c in header] for row in table]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def json_safe(value: Any) -> Any:
    """NaN and infinities to None (strict JSON), recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def write_metrics(result: EvaluationResult, out_dir: str | os.PathLike, meta: Mapping[str, Any]) -> dict[str, Path]:
    """Write ``metrics.csv`` (the table), ``per_image.csv`` and ``metrics.json`` (table, per-image, ``meta``).

    Returns:
        ``{"csv": ..., "per_image": ..., "json": ...}`` paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    header = ["group", "n-images", *result.columns]
    paths = {"csv": out / "metrics.csv", "per_image": out / "per_image.csv", "json": out / "metrics.json"}
    with open(paths["csv"], "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=header, extrasaction="ignore", restval="")
        writer.writeheader()
        writer.writerows(result.table)
    # the metrics, and the per-image entries that are not averaged (the selected candidate, the rotation error)
    cols = [c for c in ROW_INFO if c not in ("index", "group")] + result.columns
    image_cols = ["index", "group"] + [c for c in cols if any(c in r for r in result.per_image)]
    with open(paths["per_image"], "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=image_cols, extrasaction="ignore", restval="")
        writer.writeheader()
        writer.writerows(result.per_image)
    payload = {
        "protocol": result.protocol,
        "columns": result.columns,
        "better": {c: METRIC_ORDER.get(c) for c in result.columns},
        "mean": result.mean,
        "table": result.table,
        "per_image": result.per_image,
        "seconds": result.seconds,
        **meta,
    }
    paths["json"].write_text(json.dumps(json_safe(payload), indent=1), encoding="utf-8")
    return paths
