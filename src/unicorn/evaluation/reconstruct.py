"""Reconstruct user images and write, per image, the textured mesh, the pictures, the mask, the pose and a turntable.

Per input image ``<out>/<name>/``:

- ``input.png``: the framed model input (what the network saw);
- ``reconstruction.png``: the textured mesh in its predicted pose over the predicted background (hard render at
  ``view_size``; the background is the model's own, upsampled);
- ``mask.png``: the predicted silhouette (hard render, anti-aliased), white = object;
- ``mesh.obj`` + ``mesh.mtl`` + ``mesh.png`` and ``mesh.glb``: the textured mesh in the object frame
  (+Y up, the camera of azimuth 0 looks from +Z; ``pose.json`` places it in the camera frame);
- ``pose.json``: rotation ``R`` and translation ``T`` (``x_view = x_object @ R + T``, PyTorch3D view axes: +X left,
  +Y up, +Z away from the camera), and the same camera as the arguments of
  :func:`unicorn.geometry.rotations.look_at_view_transform` (``distance``, ``elevation``, ``azimuth`` in degrees,
  ``at``, ``up``; ``roll`` is informative), the anisotropic scale, the camera (field of view or focal length)
  and the probabilities of all pose candidates;
- ``turntable.gif`` and ``turntable.png`` (a strip of views): the mesh spinning about its vertical axis.

With refinement (``refine``, :func:`unicorn.objectives.refine.refine`) every file above carries the refined result,
and ``reconstruction_network.png`` and ``turntable_network.png`` keep the network's own prediction beside it.

The folder also gets ``overview.png`` (one row per image; with refinement the network's reconstruction and views
next to the refined ones), ``index.html`` and ``reconstructions.json``
(``{"provenance": ..., "images": [...]}``, each image's ``files`` naming every file written in its folder);
``pose.json`` and both of these record the provenance (command, checkpoint, package version, git commit) given to
:func:`reconstruct`. Image folders of an earlier reconstruction that a reconstruction into the same folder does not
write again stay where they are, and ``index.html`` and ``reconstructions.json`` (``earlier_folders``) name them.
"""

from __future__ import annotations

import hashlib
import html
import json
import os
import re
import sys
import unicodedata
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm.auto import tqdm

from unicorn.evaluation.pictures import image_grid, save_gif, to_uint8
from unicorn.evaluation.rendering import even_angles, hard_render, turntable
from unicorn.evaluation.viewer import install_viewer, viewer_element, viewer_script_tags
from unicorn.geometry.cameras import opencv_camera
from unicorn.geometry.rotations import look_at_rotation, look_at_view_parameters
from unicorn.io.images import RECONSTRUCTIONS_RECORD, InputImage, Rectangle
from unicorn.io.meshes import export_prediction, save_mesh
from unicorn.io.staging import OutputConflictError, check_replaceable
from unicorn.model import Prediction, Unicorn
from unicorn.objectives.refine import Refinement, RefineOptions, refine

__all__ = ["check_free", "earlier_folders", "pose_record", "reconstruct", "unique_names"]

#: the files written at the top of the output folder: no image's folder may take these names
RESERVED_NAMES = ("index.html", "overview.png", RECONSTRUCTIONS_RECORD, "_viewer")

#: largest side of a picture in overview.png (the per-image files keep the full view size)
OVERVIEW_CELL = 160

#: the files written only on request in an image's folder (a turntable GIF, the network's prediction beside a
#: refined one): an earlier run's are removed where a run writes that image's folder again without them
#: (:func:`unicorn.io.staging.staged_folder`)
OPTIONAL_FILES = ("*/turntable.gif", "*/reconstruction_network.png", "*/turntable_network.png")

#: longest output name, in bytes of UTF-8 (file systems allow 255): a longer one is cut and ends with a hash of the
#: whole
MAX_NAME = 120


def unique_names(paths: Sequence[Path]) -> list[str]:
    """File-system safe, unique output names for input files.

    The file stem; files whose stems are the same (without regard to case) take their path relative to their common
    folder instead (``a/0000.png`` and ``b/0000.png`` become ``a_0000`` and ``b_0000``), the others keep their
    stems; a numeric suffix settles what remains, and keeps names clear of :data:`RESERVED_NAMES` (the folder's own
    files). Letters and digits of any script are kept (in Unicode's composed form, NFC), every other run of
    characters but ``.``, ``-`` and ``_`` becomes ``_``. Names differ also without regard to case, and are at most
    :data:`MAX_NAME` bytes long in UTF-8.
    """
    paths = [Path(p) for p in paths]
    raw = [p.stem for p in paths]
    groups: dict[str, list[int]] = {}
    for i, p in enumerate(paths):
        groups.setdefault(unicodedata.normalize("NFC", p.stem).casefold(), []).append(i)
    for group in (g for g in groups.values() if len(g) > 1):
        common = Path(os.path.commonpath([str(paths[i].resolve().parent) for i in group]))
        for i in group:
            raw[i] = str(paths[i].resolve().relative_to(common).with_suffix(""))
    names: list[str] = []
    seen: set[str] = {n.casefold() for n in RESERVED_NAMES}
    for text in raw:
        # NFC: macOS hands out decomposed names, which would be two names for one on other file systems
        base = re.sub(r"[^\w.-]+", "_", unicodedata.normalize("NFC", text)).strip("._") or "image"
        if len(base.encode()) > MAX_NAME - 8:  # room for a numeric suffix
            cut = base.encode()[: MAX_NAME - 25].decode(errors="ignore")  # not inside a character
            base = f"{cut}_{hashlib.sha256(text.encode()).hexdigest()[:8]}"
        name, k = base, 1
        while name.casefold() in seen:
            name, k = f"{base}_{k}", k + 1
        seen.add(name.casefold())
        names.append(name)
    return names


#: how pose.json's ``opencv`` numbers are read (written into the file)
OPENCV_CONVENTION = (
    "x_cam = R @ x_object + t, camera axes +X right, +Y down, +Z forward (OpenCV, COLMAP); pixel (u, v, 1) ~ K @ "
    "x_cam with pixel centres at integers, in the photo turned upright by its EXIF orientation (K; as frame) or in "
    "input.png (K_input). x_object are the vertices of mesh.obj and mesh.glb, as for R and T."
)

#: how pose.json's numbers are read (written into the file)
POSE_CONVENTION = (
    "x_view = x_object @ R + T; view axes +X left, +Y up, +Z away from the camera (PyTorch3D). "
    "R, T = unicorn.geometry.rotations.look_at_view_transform(dist=distance, elev=elevation, azim=azimuth, "
    "at=[at], up=[up]) gives back R and T (PyTorch3D's look_at_view_transform too): azimuth 0 puts the camera "
    "on +Z, 90 on +X, positive elevation above (+Y), in degrees; at is the point of the optical axis at the "
    "object's depth (0 when the object is centred) and up the camera's +Y axis; roll (degrees) is the turn of "
    "the camera about its axis from the +Y-up camera (0: up=[0, 1, 0] gives the same camera). x_object are the "
    "vertices of mesh.obj and mesh.glb, which hold the anisotropic scale already: do not apply scale again."
)


def pose_record(model: Unicorn, pred: Prediction, index: int, frame: Rectangle | None = None) -> dict[str, Any]:
    """JSON-ready pose of one prediction: R, T, look-at parameters, scale, camera, candidate probabilities, and the
    same camera in OpenCV's convention (:func:`~unicorn.geometry.cameras.opencv_camera`); with the ``frame`` of the
    photo the input shows (:attr:`unicorn.io.InputImage.frame`), that rectangle and the OpenCV intrinsics in the
    photo's pixels."""
    R, T = pred.R[index].detach().cpu().double(), pred.T[index].detach().cpu().double()
    look = look_at_view_parameters(R, T)
    # roll: signed angle about the optical axis from the +Y-up look-at camera's Y axis to this camera's
    upright = look_at_rotation((-T @ R.T)[None], look["at"][None])[0]
    y0, y, z = upright[:, 1], R[:, 1], R[:, 2]
    roll = torch.rad2deg(torch.atan2(torch.linalg.cross(y0, y).dot(z), y0.dot(y)))
    camera = model.renderer.camera
    size = model.config["image_size"]
    K_input, R_cv, t_cv = opencv_camera(R, T, camera.focal_length, (0.0, 0.0, size, size))
    opencv = {"convention": OPENCV_CONVENTION, "R": R_cv.tolist(), "t": t_cv.tolist(), "K_input": K_input.tolist()}
    placed = {}
    if frame is not None:
        placed = {"frame": dict(zip(("x", "y", "width", "height"), frame, strict=True))}
        opencv["K"] = opencv_camera(R, T, camera.focal_length, frame)[0].tolist()
    return {
        "convention": POSE_CONVENTION,
        "R": R.tolist(),
        "T": T.tolist(),
        "azimuth": float(look["azim"]),
        "elevation": float(look["elev"]),
        "distance": float(look["dist"]),
        "at": look["at"].tolist(),
        "up": look["up"].tolist(),
        "roll": float(roll),
        "scale": pred.scale[index].detach().cpu().tolist(),
        "camera": {"fov_degrees": camera.fov, "focal_length_ndc": float(camera.focal_length)},
        "image_size": model.config["image_size"],
        "candidate_probabilities": pred.poses.probs[:, index].detach().cpu().tolist(),
        **placed,
        "opencv": opencv,
    }


def _views(
    model: Unicorn, pred: Prediction, i: int, view_size: int, angles: Sequence[float]
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Image ``i``'s hard render over its background (4, S, S) (RGB, alpha) and its textured turntable views."""
    verts, tex, R, T = pred.verts[i : i + 1], pred.texture[i : i + 1], pred.R[i : i + 1], pred.T[i : i + 1]
    bkg = None
    if pred.background is not None:
        bkg = F.interpolate(
            pred.background[i : i + 1], size=(view_size, view_size), mode="bilinear", align_corners=False
        )
    rendered = hard_render(model, verts, tex, R, T, view_size, background=bkg).images[0]
    return rendered, list(turntable(model, verts[0], tex[0], R[0], T[0], angles, view_size))


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
    provenance: Mapping[str, Any],
    network: Prediction | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Write image ``i``'s files for ``pred`` and return its record; ``network``: the network's own prediction
    that ``pred`` refines, written beside it; ``overwrite``: replace the meshes of an earlier call and remove its
    :data:`OPTIONAL_FILES` that this call does not write."""
    folder.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}

    def save(name: str, array: np.ndarray) -> None:
        Image.fromarray(array).save(folder / name)
        files[name.split(".")[0]] = name

    strip_angles = even_angles(strip_views)
    rendered, strip = _views(model, pred, i, view_size, strip_angles)
    save("input.png", to_uint8(item.image))
    save("reconstruction.png", to_uint8(rendered[:3]))
    save("mask.png", to_uint8(rendered[3:]))

    mesh = export_prediction(model, pred, i, name="mesh")
    for suffix in (".obj", ".glb"):
        for written in save_mesh(mesh, folder / f"mesh{suffix}", overwrite=overwrite):  # the OBJ's MTL and PNG too
            files[written.name] = written.name
    pose = pose_record(model, pred, i, item.frame)
    (folder / "pose.json").write_text(json.dumps({**pose, "provenance": dict(provenance)}, indent=1), encoding="utf-8")
    files["pose"] = "pose.json"

    verts, tex, R, T = pred.verts[i], pred.texture[i], pred.R[i], pred.T[i]
    shaded = turntable(model, verts, tex, R, T, strip_angles, view_size, shaded=True)
    save("turntable.png", np.concatenate([to_uint8(f[:3]) for f in strip], axis=1))
    if turntable_frames > 0:
        frames = turntable(model, verts, tex, R, T, turntable_frames, view_size)
        save_gif(frames, folder / "turntable.gif")
        files["turntable_gif"] = "turntable.gif"
    cell = min(view_size, OVERVIEW_CELL)
    row = [to_uint8(item.image, cell), to_uint8(rendered[:3], cell), to_uint8(rendered[3:], cell)]
    row += [to_uint8(f[:3], cell) for f in strip] + [to_uint8(f[:3], cell) for f in shaded]
    if network is not None:
        # the network's prediction beside the refined one
        net_rendered, net_strip = _views(model, network, i, view_size, strip_angles)
        save("reconstruction_network.png", to_uint8(net_rendered[:3]))
        save("turntable_network.png", np.concatenate([to_uint8(f[:3]) for f in net_strip], axis=1))
        row += [to_uint8(net_rendered[:3], cell)] + [to_uint8(f[:3], cell) for f in net_strip]
    if overwrite:
        # an earlier call's optional files that this one does not write would mix two runs in one folder
        for name in {Path(pattern).name for pattern in OPTIONAL_FILES} - set(files.values()):
            if (folder / name).is_file():
                (folder / name).unlink()
    return {
        "name": item.name,
        "source": os.path.abspath(item.path),
        "cropped_from_alpha_or_box": item.cropped,
        "folder": folder.name,  # within the output folder, which may be moved (it is: out of the staging folder)
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
    provenance: Mapping[str, Any] | None = None,
    refine_options: RefineOptions | None = None,
    overwrite: bool = False,
    earlier: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Reconstruct preprocessed images and write their outputs (see the module docstring).

    Args:
        model: the model.
        items: framed inputs (:func:`unicorn.io.load_input`), each (3, S, S) with S the model's size; each
            ``name`` is its folder's, so names must differ (also without regard to case; :func:`unique_names`).
        out_dir: output folder (one sub-folder per image).
        device: where to run.
        batch_size: images per forward pass.
        view_size: side of the pictures.
        turntable_frames: frames of ``turntable.gif`` (0: no GIF).
        strip_views: views in ``turntable.png`` (evenly spaced over a turn).
        average_texture: predict mean-colour textures.
        progress: show a progress bar.
        provenance: where the results come from (:func:`unicorn.io.provenance.provenance`: command,
            checkpoint, versions), recorded in every JSON file and the HTML page; default: the calling process.
        refine_options: refine each prediction against its image (:func:`unicorn.objectives.refine.refine`) and write
            the refined result, the network's beside it; None (or 0 steps): the network's prediction.
        overwrite: replace the outputs of an earlier call in ``out_dir`` (an image's folder, the overview, the
            record; in the folder of an image written again, the earlier call's :data:`OPTIONAL_FILES` that this
            call does not write are removed, other files of the folder stay); otherwise they are an error raised
            before anything is written.
        earlier: the image folders of an earlier reconstruction that stay beside this one's, named in
            ``index.html`` and ``reconstructions.json``; None: those in ``out_dir`` (:func:`earlier_folders`).

    Returns:
        one record per image (name, source, folder within ``out_dir``, written files, pose angles, and with
        refinement the objective before and after it); also written to ``<out>/reconstructions.json``.

    Raises:
        ValueError: two images of the same name, or a name that is not one folder name or is one of the output
            folder's own files (before anything is written).
        OutputConflictError: ``out_dir`` holds an earlier call's outputs and ``overwrite`` is False, or an entry
            that an output cannot replace (:func:`check_free`; before anything is written).
    """
    out = Path(out_dir)
    _check_names(items)
    check_free(out, [it.name for it in items], overwrite)
    earlier = earlier_folders(out, [it.name for it in items]) if earlier is None else list(earlier)
    out.mkdir(parents=True, exist_ok=True)
    if provenance is None:
        from unicorn.io.provenance import command_line
        from unicorn.io.provenance import provenance as record

        provenance = record(command_line(Path(sys.argv[0]).name, sys.argv[1:]))
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
        network = result = None
        if refine_options is not None and refine_options.steps > 0:
            with torch.enable_grad():
                result = refine(model, images, refine_options, initial=pred, average_texture=average_texture)
            network, pred = pred, result.prediction
        for i, item in enumerate(chunk):
            folder = out / item.name
            record = _write_one(
                model,
                pred,
                i,
                item,
                folder,
                view_size,
                turntable_frames,
                strip_views,
                device,
                provenance,
                network,
                overwrite,
            )
            if result is not None:
                record["refinement"] = _refinement_record(result, i, refine_options)  # type: ignore[arg-type]
            records.append(record)
            bar.update()
    bar.close()
    _write_overview(out, records, view_size, provenance, earlier)
    return records


#: what :func:`reconstruct` writes beside the images' folders
_OVERVIEW_FILES = ("overview.png", "index.html", RECONSTRUCTIONS_RECORD)


def _check_names(items: Sequence[InputImage]) -> None:
    """Refuse image names that cannot each be a folder of their own in the output folder: a path rather than one
    name, one of :data:`RESERVED_NAMES`, or a name that two images share (without regard to case, as
    :func:`unique_names` compares them).

    Raises:
        ValueError: names the first such name.
    """
    seen: dict[str, InputImage] = {}
    reserved = {n.casefold() for n in RESERVED_NAMES}
    for item in items:
        name = item.name
        if not name or name in (".", "..") or Path(name).name != name or "/" in name or "\\" in name:
            raise ValueError(f"image name {name!r} ({item.path}) is not a folder name: give each image a plain name")
        key = unicodedata.normalize("NFC", name).casefold()
        if key in reserved:
            raise ValueError(
                f"image name {name!r} ({item.path}) is one of the output folder's own files "
                f"({', '.join(RESERVED_NAMES)}); unique_names gives names clear of them"
            )
        if key in seen:
            raise ValueError(
                f"images {seen[key].path} and {item.path} are both named {name!r} (without regard to case): each needs "
                "a folder of its own; unique_names gives distinct names"
            )
        seen[key] = item


def check_free(out: str | os.PathLike, names: Sequence[str], overwrite: bool = False) -> None:
    """Check, before any work, that :func:`reconstruct` can write images of these names into ``out``.

    Refused always: an entry of ``out`` that an output cannot replace, as
    :func:`unicorn.io.staging.staged_folder` would refuse it once the work is done (a file or a link where an
    image's folder or ``_viewer`` goes, a folder where one of :data:`_OVERVIEW_FILES` goes). Refused unless
    ``overwrite``: an earlier call's outputs, a non-empty folder of one of the images or one of
    :data:`_OVERVIEW_FILES`.

    Raises:
        OutputConflictError: names the first such entry, or the first few outputs.
    """
    out = Path(out)
    if not out.is_dir():
        return
    check_replaceable(out, folders=[*names, "_viewer"], files=_OVERVIEW_FILES)
    if overwrite:
        return
    taken = [out / name for name in names if (out / name).is_dir() and any((out / name).iterdir())]
    taken += [out / name for name in _OVERVIEW_FILES if (out / name).exists()]
    if taken:
        listed = ", ".join(p.name for p in taken[:4]) + (f" and {len(taken) - 4} more" if len(taken) > 4 else "")
        raise OutputConflictError(
            f"{out} holds the outputs of an earlier reconstruction ({listed}); pass overwrite=True to replace them, "
            "or write elsewhere"
        )


def earlier_folders(out: str | os.PathLike, names: Sequence[str]) -> list[str]:
    """The image folders of an earlier reconstruction in ``out`` (sub-folders holding a ``pose.json``) that images
    of these ``names`` do not write again, sorted: a reconstruction into ``out`` leaves them in place (they may be
    the user's to keep) and names them, as its overview does not show them."""
    out = Path(out)
    if not out.is_dir():
        return []
    written = {unicodedata.normalize("NFC", n).casefold() for n in names}
    return sorted(
        entry.name
        for entry in out.iterdir()
        if not entry.name.startswith(".")
        and unicodedata.normalize("NFC", entry.name).casefold() not in written
        and entry.is_dir()
        and (entry / "pose.json").is_file()
    )


def _refinement_record(result: Refinement, i: int, options: RefineOptions) -> dict[str, Any]:
    """What refining image ``i`` did: its settings and the objective before and after."""
    losses = result.losses[:, i]
    return {
        "steps": options.steps,
        "parts": list(options.parts),
        "objective_network": float(losses[0]),
        "objective_refined": float(result.objective[i]),  # that of the result written: the lowest, not the last
    }


def _write_overview(
    out: Path,
    records: list[dict[str, Any]],
    view_size: int,
    provenance: Mapping[str, Any],
    earlier: Sequence[str] = (),
) -> None:
    """``overview.png`` and ``index.html`` from the records' pictures (popped from them), and
    ``reconstructions.json`` (the records, and the ``earlier`` image folders left beside them)."""
    rows = [r.pop("_row") for r in records]
    angles = records[0].pop("_angles") if records else []
    for r in records[1:]:
        r.pop("_angles")
    if rows:
        labels = ["input", "reconstruction", "mask"]
        labels += [f"textured {a:g}°" for a in angles] + [f"shape {a:g}°" for a in angles]
        if len(rows[0]) > len(labels):
            labels += ["network"] + [f"network {a:g}°" for a in angles]
        image_grid(rows, labels, [r["name"] for r in records]).save(out / "overview.png")
        _write_index(out, records, labels, view_size, provenance, earlier)
    record = {"provenance": provenance, "images": records}
    if earlier:
        record["earlier_folders"] = list(earlier)
    (out / RECONSTRUCTIONS_RECORD).write_text(json.dumps(record, indent=1), encoding="utf-8")


def _write_index(
    out: Path,
    records: Sequence[dict[str, Any]],
    labels: Sequence[str],
    view_size: int,
    provenance: Mapping[str, Any],
    earlier: Sequence[str] = (),
) -> None:
    """``index.html``: per image its pictures, turntable, an interactive 3D view, and links to the meshes and pose;
    a note naming the ``earlier`` image folders, which it does not show."""
    rows = []
    size = min(view_size, 192)
    n_views = sum(label.startswith("textured") for label in labels)
    refined = ""
    if any("refinement" in r for r in records):
        refined = (
            " Every result is refined against its image; the network's own reconstruction (before refinement) is "
            "shown beside it, and in overview.png its views after the refined ones."
        )
    head_script, body_script = viewer_script_tags(install_viewer(out))
    for r in records:
        name, url = html.escape(r["name"]), html.escape(quote(r["name"]))
        shown = ("input", "reconstruction", "reconstruction_network", "mask")
        pics = [f"{url}/{r['files'][k]}" for k in shown if k in r["files"]]
        if "turntable_gif" in r["files"]:
            pics.append(f"{url}/{r['files']['turntable_gif']}")
        cells = "".join(f'<td><img src="{p}" width="{size}" height="{size}"></td>' for p in pics)
        pose = r["pose"]
        glb = out / r["folder"] / r["files"]["mesh.glb"]
        orbit = (pose["azimuth"], pose["elevation"])
        viewer = viewer_element(glb, max(size, 160), alt=f"textured mesh of {r['name']}", orbit=orbit)
        cells += f"<td>{viewer}</td>"
        links = " ".join(
            f'<a href="{url}/{html.escape(r["files"][k])}">{html.escape(k)}</a>'
            for k in ("mesh.obj", "mesh.glb", "pose", "turntable")
            if k in r["files"]
        )
        azim, elev, roll = (pose[k] if abs(pose[k]) >= 0.5 else 0.0 for k in ("azimuth", "elevation", "roll"))
        caption = f"<b>{name}</b><br>azim {azim:.0f}°, elev {elev:.0f}°, roll {roll:.0f}°<br>{links}"
        rows.append(f"<tr><td class='cap'>{caption}</td>{cells}</tr>")
    kept = ""
    if earlier:
        links = ", ".join(f'<a href="{html.escape(quote(n))}/">{html.escape(n)}/</a>' for n in earlier)
        kept = f"<p>Not shown: image folders of an earlier reconstruction, left in this folder: {links}.</p>"
    origin = "".join(
        f"<dt>{html.escape(str(k))}</dt><dd><code>{html.escape(str(v))}</code></dd>" for k, v in provenance.items()
    )
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>unicorn reconstructions</title><style>
body{{font-family:system-ui,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1200px;padding:0 1em;color:#222}}
td{{padding:.3em;vertical-align:top}} .cap{{font-size:.9em;min-width:12em}}
dl{{display:grid;grid-template-columns:max-content auto;gap:.2em 1em;font-size:.85em}} dt{{font-weight:600}}
</style>{head_script}</head><body><h1>Reconstructions</h1>
<p>Input, reconstruction, predicted mask, turntable and an interactive 3D view (drag to rotate, scroll to zoom;
it opens from the predicted viewpoint) per image; <a href="overview.png">overview.png</a> shows
the meshes from {n_views} viewpoints, textured and untextured.{refined}</p>
<table>{"".join(rows)}</table>{kept}
<h2>Provenance</h2><dl>{origin}</dl>
{body_script}</body></html>
"""
    (out / "index.html").write_text(page, encoding="utf-8")
