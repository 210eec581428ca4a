"""Reconstruct user images and write, per image, the textured mesh, the pictures, the mask, the pose and a turntable.

Per input image ``<out>/<name>/``:

- ``input.png``: the framed model input (what the network saw);
- ``reconstruction.png``: the textured mesh in its predicted pose over the predicted background (hard render at
  ``view_size``; the background is the model's own, upsampled);
- ``mask.png``: the predicted silhouette (hard render, anti-aliased), white = object;
- ``mesh.obj`` + ``mesh.mtl`` + ``mesh.png`` and ``mesh.glb``: the textured mesh in the object frame
  (+Y up, the camera of azimuth 0 looks from +Z; ``pose.json`` places it in the camera frame);
- ``pose.json``: rotation ``R`` and translation ``T`` (``x_view = x_object @ R + T``, PyTorch3D view axes: +X left,
  +Y up, +Z away from the camera), azimuth / elevation / roll in degrees, the anisotropic scale, the camera
  (field of view or focal length) and the probabilities of all pose candidates;
- ``turntable.gif`` and ``turntable.png`` (a strip of views): the mesh spinning about its vertical axis.

The folder also gets ``overview.png`` (one row per image) and ``index.html``.
"""

from __future__ import annotations

import html
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm.auto import tqdm

from unicorn.evaluation.rendering import even_angles, hard_render, turntable
from unicorn.evaluation.report import image_grid, save_gif, to_uint8
from unicorn.io.images import InputImage
from unicorn.metrics import rotation_to_azim_elev_roll
from unicorn.model import Prediction, Unicorn, export_prediction, save_mesh

__all__ = ["pose_record", "reconstruct", "unique_names"]

#: the files written at the top of the output folder: no image's folder may take these names
RESERVED_NAMES = ("index.html", "overview.png", "reconstructions.json")

#: largest side of a picture in overview.png (the per-image files keep the full view size)
OVERVIEW_CELL = 160


def unique_names(paths: Sequence[Path]) -> list[str]:
    """File-system safe, unique output names for input files.

    The file stem when stems are unique; otherwise the path relative to the inputs' common folder (``a/0000.png``
    and ``b/0000.png`` become ``a_0000`` and ``b_0000``); a numeric suffix settles what remains, and keeps names
    clear of :data:`RESERVED_NAMES` (the folder's own files). Names differ also without regard to case.
    """
    paths = [Path(p) for p in paths]
    if len({p.stem for p in paths}) == len(paths):
        raw = [p.stem for p in paths]
    else:
        common = Path(os.path.commonpath([str(p.resolve().parent) for p in paths]))
        raw = [str(p.resolve().relative_to(common).with_suffix("")) for p in paths]
    names: list[str] = []
    seen: set[str] = {n.lower() for n in RESERVED_NAMES}
    for text in raw:
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "image"
        name, k = base, 1
        while name.lower() in seen:
            name, k = f"{base}_{k}", k + 1
        seen.add(name.lower())
        names.append(name)
    return names


def pose_record(model: Unicorn, pred: Prediction, index: int) -> dict[str, Any]:
    """JSON-ready pose of one prediction: R, T, angles, scale, camera, candidate probabilities."""
    R, T = pred.R[index].detach().cpu(), pred.T[index].detach().cpu()
    azim, elev, roll = (float(a) for a in rotation_to_azim_elev_roll(R))
    camera = model.renderer.camera
    return {
        "convention": "x_view = x_object @ R + T; view axes +X left, +Y up, +Z away from the camera (PyTorch3D)",
        "R": R.tolist(),
        "T": T.tolist(),
        "azimuth": azim,
        "elevation": elev,
        "roll": roll,
        "distance": float(T.norm()),
        "scale": pred.scale[index].detach().cpu().tolist(),
        "camera": {"fov_degrees": camera.fov, "focal_length_ndc": float(camera.focal_length)},
        "image_size": model.config["image_size"],
        "candidate_probabilities": pred.poses.probs[:, index].detach().cpu().tolist(),
    }


def _write_one(
    model: Unicorn,
    pred: Prediction,
    i: int,
    item: InputImage,
    folder: Path,
    view_size: int,
    turntable_frames: int,
    strip_views: int,
    device: torch.device,
) -> dict[str, Any]:
    folder.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}

    def save(name: str, array: np.ndarray) -> None:
        Image.fromarray(array).save(folder / name)
        files[name.split(".")[0]] = name

    verts, tex, R, T = pred.verts[i : i + 1], pred.texture[i : i + 1], pred.R[i : i + 1], pred.T[i : i + 1]
    bkg = None
    if pred.background is not None:
        bkg = F.interpolate(
            pred.background[i : i + 1], size=(view_size, view_size), mode="bilinear", align_corners=False
        )
    rendered = hard_render(model, verts, tex, R, T, view_size, background=bkg).images[0]
    save("input.png", to_uint8(item.image))
    save("reconstruction.png", to_uint8(rendered[:3]))
    save("mask.png", to_uint8(rendered[3:]))

    mesh = export_prediction(model, pred, i, name="mesh")
    for suffix in (".obj", ".glb"):
        written = save_mesh(mesh, folder / f"mesh{suffix}")
        files[f"mesh{suffix}"] = written[0].name
    pose = pose_record(model, pred, i)
    (folder / "pose.json").write_text(json.dumps(pose, indent=1))
    files["pose"] = "pose.json"

    strip_angles = even_angles(strip_views)
    strip = turntable(model, verts[0], tex[0], R[0], T[0], strip_angles, view_size)
    shaded = turntable(model, verts[0], tex[0], R[0], T[0], strip_angles, view_size, shaded=True)
    save("turntable.png", np.concatenate([to_uint8(f[:3]) for f in strip], axis=1))
    if turntable_frames > 0:
        frames = turntable(model, verts[0], tex[0], R[0], T[0], turntable_frames, view_size)
        save_gif(frames, folder / "turntable.gif")
        files["turntable_gif"] = "turntable.gif"
    cell = min(view_size, OVERVIEW_CELL)
    row = [to_uint8(item.image, cell), to_uint8(rendered[:3], cell), to_uint8(rendered[3:], cell)]
    row += [to_uint8(f[:3], cell) for f in strip] + [to_uint8(f[:3], cell) for f in shaded]
    return {
        "name": item.name,
        "source": str(item.path),
        "cropped_from_alpha_or_box": item.cropped,
        "folder": str(folder),
        "files": files,
        "pose": {k: pose[k] for k in ("azimuth", "elevation", "roll", "distance")},
        "_row": row,
        "_angles": strip_angles,
    }


@torch.no_grad()
def reconstruct(
    model: Unicorn,
    items: Sequence[InputImage],
    out_dir: str | os.PathLike,
    device: str | torch.device = "cpu",
    batch_size: int = 16,
    view_size: int = 256,
    turntable_frames: int = 24,
    strip_views: int = 4,
    average_texture: bool = False,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Reconstruct preprocessed images and write their outputs (see the module docstring).

    Args:
        model: the model.
        items: framed inputs (:func:`unicorn.io.load_input`), each (3, S, S) with S the model's size.
        out_dir: output folder (one sub-folder per image).
        device: where to run.
        batch_size: images per forward pass.
        view_size: side of the pictures.
        turntable_frames: frames of ``turntable.gif`` (0: no GIF).
        strip_views: views in ``turntable.png`` (evenly spaced over a turn).
        average_texture: predict mean-colour textures.
        progress: show a progress bar.

    Returns:
        one record per image (name, source, folder, written files, pose angles); also written to
        ``<out>/reconstructions.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(device)
    model = model.to(device).eval()
    size = model.config["image_size"]
    records: list[dict[str, Any]] = []
    bar = tqdm(total=len(items), desc="reconstruct", unit="img", disable=not progress)
    for start in range(0, len(items), batch_size):
        chunk = items[start : start + batch_size]
        images = torch.stack([it.image for it in chunk]).to(device)
        if images.shape[-1] != size:
            raise ValueError(f"inputs must be framed at the model's size {size}, got {tuple(images.shape[-2:])}")
        pred = model.predict(images, average_texture=average_texture)
        for i, item in enumerate(chunk):
            records.append(
                _write_one(model, pred, i, item, out / item.name, view_size, turntable_frames, strip_views, device)
            )
            bar.update()
    bar.close()
    rows = [r.pop("_row") for r in records]
    angles = records[0].pop("_angles") if records else []
    for r in records[1:]:
        r.pop("_angles")
    if rows:
        labels = ["input", "reconstruction", "mask"]
        labels += [f"textured {a:g}°" for a in angles] + [f"shape {a:g}°" for a in angles]
        image_grid(rows, labels, [r["name"] for r in records]).save(out / "overview.png")
        _write_index(out, records, labels, view_size)
    (out / "reconstructions.json").write_text(json.dumps(records, indent=1))
    return records


def _write_index(out: Path, records: Sequence[dict[str, Any]], labels: Sequence[str], view_size: int) -> None:
    """``index.html``: per image its pictures, turntable and links to the meshes and pose."""
    rows = []
    size = min(view_size, 192)
    for r in records:
        name = html.escape(r["name"])
        pics = [f"{name}/{r['files'][k]}" for k in ("input", "reconstruction", "mask") if k in r["files"]]
        if "turntable_gif" in r["files"]:
            pics.append(f"{name}/{r['files']['turntable_gif']}")
        cells = "".join(f'<td><img src="{p}" width="{size}" height="{size}"></td>' for p in pics)
        links = " ".join(
            f'<a href="{name}/{html.escape(r["files"][k])}">{html.escape(k)}</a>'
            for k in ("mesh.obj", "mesh.glb", "pose", "turntable")
            if k in r["files"]
        )
        pose = r["pose"]
        caption = (
            f"<b>{name}</b><br>azim {pose['azimuth']:.0f}°, elev {pose['elevation']:.0f}°, "
            f"roll {pose['roll']:.0f}°<br>{links}"
        )
        rows.append(f"<tr><td class='cap'>{caption}</td>{cells}</tr>")
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>unicorn reconstructions</title><style>
body{{font-family:system-ui,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1200px;padding:0 1em;color:#222}}
td{{padding:.3em;vertical-align:top}} .cap{{font-size:.9em;min-width:12em}}
</style></head><body><h1>Reconstructions</h1>
<p>Input, reconstruction, predicted mask and turntable per image; <a href="overview.png">overview.png</a> shows
the meshes from {(len(labels) - 3) // 2} viewpoints, textured and untextured.</p>
<table>{"".join(rows)}</table></body></html>
"""
    (out / "index.html").write_text(page, encoding="utf-8")
