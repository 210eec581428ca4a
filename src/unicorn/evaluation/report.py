"""The visual report of an evaluation (a PNG grid and an HTML page); the metric files are :mod:`.metric_files`.

The report shows, for a few evaluated images, the input, the model's reconstruction, the predicted silhouette
against the ground-truth mask, and the predicted mesh from several viewpoints, textured and as lit untextured
geometry (which shows the shape without the texture's help); the HTML page adds the metric table, what each
column means, the run's settings, a turntable animation and an interactive 3D view (drag to rotate, scroll to
zoom; :mod:`unicorn.evaluation.viewer`) per image. Its images are PNG / GIF files in a ``report/`` folder beside
it, referenced by relative paths, and the viewer's script is copied to ``_viewer/``, so the folder can be copied,
served or opened from disk as is, without a network.
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from unicorn.config.schema import REPORT_TURNTABLE_FRAMES
from unicorn.evaluation.interface import EvaluableModel
from unicorn.evaluation.metric_files import format_value, json_safe
from unicorn.evaluation.pictures import image_grid, mask_overlay, save_gif, to_uint8
from unicorn.evaluation.protocols import METRIC_HELP, METRIC_ORDER, EvaluationResult, Sample
from unicorn.evaluation.rendering import even_angles, turntable
from unicorn.evaluation.viewer import VIEWER_FILES, install_viewer, viewer_element, viewer_script_tags
from unicorn.geometry.rotations import look_at_view_parameters
from unicorn.io.meshes import glb_bytes, textured_mesh

__all__ = ["REPORT_FILES", "sample_views", "write_report"]

#: what :func:`write_report` writes into the output folder, only where there are samples to show: an evaluation
#: without a report, or with fewer samples, removes an earlier one's, and leaves other files in ``report/`` and
#: ``_viewer/`` where they are (:func:`unicorn.io.staging.staged_folder`)
REPORT_FILES = (
    "report.html",
    "report.png",
    "report/sample[0-9]*_*",
    *(f"_viewer/{name}" for name in VIEWER_FILES),
)


def _sample_viewer(model: EvaluableModel, sample: Sample, size: int) -> str:
    """The interactive view of a sample's textured mesh, opening from its camera's azimuth and elevation."""
    tmpl = model.template
    mesh = textured_mesh(sample.verts, tmpl.faces, tmpl.face_uvs, sample.texture, align_corners=not tmpl.wrap_u)
    look = look_at_view_parameters(sample.R.double(), sample.T.double())
    return viewer_element(
        glb_bytes(mesh, name=f"sample{sample.index}"),
        size,
        alt=f"textured mesh of image {sample.index}",
        orbit=(float(look["azim"]), float(look["elev"])),
    )


def sample_views(
    model: EvaluableModel,
    sample: Sample,
    view_size: int,
    angles: Sequence[float],
    device: torch.device,
) -> tuple[list[np.ndarray], list[str]]:
    """The report row of one sample: input, reconstruction, mask, textured and shaded views at ``angles``."""
    v, tex = sample.verts.to(device), sample.texture.to(device)
    R, T = sample.R.to(device), sample.T.to(device)
    textured = turntable(model, v, tex, R, T, list(angles), view_size)
    shaded = turntable(model, v, tex, R, T, list(angles), view_size, shaded=True)
    cells = [
        to_uint8(sample.image, view_size),
        to_uint8(sample.reconstruction, view_size),
        to_uint8(mask_overlay(sample.alpha, sample.mask), view_size),
    ]
    labels = ["input", "reconstruction", "mask (GT: blue/red)" if sample.mask is not None else "mask"]
    cells += [to_uint8(f[:3]) for f in textured] + [to_uint8(f[:3]) for f in shaded]
    labels += [f"textured {a:g}°" for a in angles] + [f"shape {a:g}°" for a in angles]
    return cells, labels


#: per-image scores shown first beside a sample
_KEY_SCORES = ("chamfer-L1", "chamfer-L1-ICP", "mask-iou", "rec-mse")


def _row_label(sample: Sample, columns: Sequence[str], limit: int | None = 4) -> str:
    """The image's index and group, then its per-image scores (at most ``limit``; None: all): the key scores,
    the others in table order, then those without a column of their own (``rot-err``)."""
    lines = [f"#{sample.index} {sample.group}"]
    scores = [c for c in sample.scores if c != "candidate"]  # a label, not a score
    order = [c for c in _KEY_SCORES if c in scores] + [c for c in columns if c in scores and c not in _KEY_SCORES]
    order += [c for c in scores if c not in order]
    lines += [f"{c}: {format_value(sample.scores[c], c)}" for c in order][:limit]
    return "\n".join(lines)


def _html_table(result: EvaluationResult) -> str:
    header = ["group", "n-images", *result.columns]
    arrow = {"lower": " ↓", "higher": " ↑"}
    th = "".join(
        f'<th title="{html.escape(METRIC_HELP.get(c, ""))}">'
        f"{html.escape(c)}{arrow.get(METRIC_ORDER.get(c, ''), '')}</th>"
        for c in header
    )
    body = []
    for row in result.table:
        cls = ' class="mean"' if row is result.table[-1] else ""
        cells = "".join(f"<td>{html.escape(format_value(row.get(c, float('nan')), c))}</td>" for c in header)
        body.append(f"<tr{cls}>{cells}</tr>")
    return f"<table><thead><tr>{th}</tr></thead><tbody>{''.join(body)}</tbody></table>"


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1400px;
color:#222;padding:0 1em} h1{font-size:1.5em;margin-bottom:.2em} .sub{color:#666;margin-top:0}
table{border-collapse:collapse;margin:1em 0;font-variant-numeric:tabular-nums}
th,td{border-bottom:1px solid #ddd;padding:.35em .8em;text-align:right} th:first-child,td:first-child{text-align:left}
th{background:#f4f4f6;cursor:help} tr.mean td{font-weight:600;border-top:2px solid #999}
.samples td{text-align:center;vertical-align:top;padding:.3em} .samples img{display:block;image-rendering:auto}
.samples .cap{font-size:.8em;color:#555;text-align:left;white-space:pre-line;min-width:9em}
dl{display:grid;grid-template-columns:max-content auto;gap:.2em 1em;font-size:.9em} dt{font-weight:600}
details{margin:1em 0} code{background:#f4f4f6;padding:0 .3em}
"""


def write_report(
    model: EvaluableModel,
    result: EvaluationResult,
    out_dir: str | os.PathLike,
    title: str,
    meta: Mapping[str, Any],
    view_size: int = 128,
    angles: Sequence[float] | None = None,
    turntable_frames: int = REPORT_TURNTABLE_FRAMES,
    device: str | torch.device = "cpu",
    interactive: bool = True,
) -> dict[str, Path]:
    """Write ``report.png`` (the sample grid) and ``report.html`` (table, legend, samples, settings).

    Args:
        model: the evaluated model (to render the meshes).
        result: :func:`~unicorn.evaluation.evaluate`'s output.
        out_dir: folder of the report (images go to ``out_dir/report/``).
        title: page title.
        meta: settings shown at the bottom (checkpoint, dataset, options...).
        view_size: side of every picture.
        angles: spin angles of the mesh views (default 0, 120, 240 degrees).
        turntable_frames: frames of the per-sample turntable GIF (0: none).
        device: where to render.
        interactive: add an interactive 3D view of every sample's textured mesh (its GLB, embedded), opening at
            the predicted viewpoint.

    Returns:
        ``{"html": ..., "png": ...}`` (``png`` absent when there are no samples).
    """
    out = Path(out_dir)
    assets = out / "report"
    assets.mkdir(parents=True, exist_ok=True)
    device = torch.device(device)
    model = model.to(device).eval()
    angles = list(angles) if angles is not None else even_angles(3)
    paths: dict[str, Path] = {}
    grid_rows, row_labels, sample_html = [], [], []
    labels: list[str] = []
    with torch.no_grad():
        for k, sample in enumerate(result.samples):
            cells, labels = sample_views(model, sample, view_size, angles, device)
            grid_rows.append(cells)
            row_labels.append(_row_label(sample, result.columns))
            files = _save_sample_files(model, sample, k, cells, labels, assets, view_size, turntable_frames, device)
            caption = html.escape(_row_label(sample, result.columns, limit=None))
            cells_html = "".join(
                f'<td><img src="report/{n}" width="{view_size}" height="{view_size}" alt="{html.escape(lb)}"></td>'
                for lb, n in files
            )
            if interactive:
                # first, beside the caption: visible without scrolling the wide table sideways
                cells_html = f"<td>{_sample_viewer(model, sample, max(view_size, 160))}</td>" + cells_html
            sample_html.append(f'<tr><td class="cap">{caption}</td>{cells_html}</tr>')
    if grid_rows:
        paths["png"] = out / "report.png"
        image_grid(grid_rows, labels, row_labels).save(paths["png"])
    scripts = ("", "")
    samples_block = ""
    if grid_rows:
        header_cells = "".join(f"<th>{html.escape(lb)}</th>" for lb in labels)
        if turntable_frames > 0:
            header_cells += "<th>turntable</th>"
        if interactive:
            header_cells = '<th title="drag to rotate, scroll to zoom">3D view (drag, scroll)</th>' + header_cells
            scripts = viewer_script_tags(install_viewer(out))
        samples_block = _samples_block(header_cells, sample_html)
    paths["html"] = out / "report.html"
    # a file name that is not UTF-8 (its bytes kept as surrogates) is shown as its JSON escape, "\udce9"
    page = _page(result, title, meta, samples_block, *scripts)
    paths["html"].write_text(page, encoding="utf-8", errors="backslashreplace")
    return paths


def _save_sample_files(
    model: EvaluableModel,
    sample: Sample,
    k: int,
    cells: Sequence[np.ndarray],
    labels: Sequence[str],
    assets: Path,
    view_size: int,
    turntable_frames: int,
    device: torch.device,
) -> list[tuple[str, str]]:
    """Sample ``k``'s pictures (and turntable GIF) in ``assets``: ``(label, file name)`` of each."""
    names = []
    for label, cell in zip(labels, cells):
        slug = label.split(" (")[0].replace(" ", "_").replace("°", "")
        name = f"sample{k:02d}_{slug}.png"
        Image.fromarray(cell).save(assets / name)
        names.append((label, name))
    if turntable_frames > 0:
        v, tex, R, T = (x.to(device) for x in (sample.verts, sample.texture, sample.R, sample.T))
        frames = turntable(model, v, tex, R, T, turntable_frames, view_size)
        names.append(("turntable", save_gif(frames, assets / f"sample{k:02d}_turntable.gif").name))
    return names


def _samples_block(header_cells: str, sample_html: Sequence[str]) -> str:
    """The report's samples section: an explanation and the table of sample rows under ``header_cells``."""
    return (
        f'<h2>Samples</h2><p class="sub">Mesh views spin the predicted mesh about its vertical axis in front of '
        f"the predicted camera (0° = the input view). Mask: dark = predicted and ground truth, red = predicted "
        f"only, blue = ground truth only.</p>"
        f'<table class="samples"><thead><tr><th></th>{header_cells}</tr></thead><tbody>{"".join(sample_html)}'
        f'</tbody></table><p><a href="report.png">All samples as one picture (report.png)</a></p>'
    )


def _page(
    result: EvaluationResult,
    title: str,
    meta: Mapping[str, Any],
    samples_block: str,
    head_script: str,
    body_script: str,
) -> str:
    """The HTML page: title, metric table, the columns' legend, the samples, the settings (``meta``)."""
    better = {"lower": " (lower is better)", "higher": " (higher is better)"}
    legend = "".join(
        f"<dt>{html.escape(c)}</dt>"
        f"<dd>{html.escape(METRIC_HELP.get(c, ''))}{better.get(METRIC_ORDER.get(c, ''), '')}</dd>"
        for c in ["n-images", *result.columns]
    )
    # the settings as written (a folder "données" not as "donn\u00e9es")
    values = {k: json.dumps(json_safe(v), ensure_ascii=False) for k, v in meta.items()}
    settings = "".join(
        f"<dt>{html.escape(str(k))}</dt><dd><code>{html.escape(text)}</code></dd>" for k, text in values.items()
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title><style>{_CSS}</style>
{head_script}</head>
<body><h1>{html.escape(title)}</h1>
<p class="sub">{html.escape(result.protocol)} protocol, {result.mean["n-images"]} images,
{result.seconds:.1f} s</p>
<h2>Metrics</h2>{_html_table(result)}
<details><summary>What the columns mean</summary><dl>{legend}</dl></details>
{samples_block}
<h2>Settings</h2><dl>{settings}</dl>
<p class="sub">Files: <a href="metrics.csv">metrics.csv</a>, <a href="metrics.json">metrics.json</a>,
<a href="per_image.csv">per_image.csv</a></p>
{body_script}</body></html>
"""
