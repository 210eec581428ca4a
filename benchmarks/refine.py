"""Test-time refinement scored on views it never saw: refine on one view of each object, score on the others.

The synthetic benchmark renders every object from 24 views with known cameras. Each object is reconstructed from
one view (unicorn-eval's fixed random view of the object, seed 0) and refined on it
(:func:`unicorn.objectives.refine.refine`); the refined mesh, texture and pose are then scored

- on the input view (what the refinement fitted): reconstruction error, mask IoU, colour ratio;
- on the 23 other views (what it must not overfit): the same three, with the object placed at each novel
  camera by :func:`novel_view_poses`;
- in 3D: Chamfer-L1 x10 with the predicted pose (the mesh placed in the ground-truth frame through the predicted
  and ground-truth input cameras) and after ICP (:func:`unicorn.metrics.evaluate_meshes`).

Metrics as unicorn-eval's: the mask IoU of the hard render (3 x 3 samples per pixel) against the ground-truth
mask; the colour ratio on mask interiors (:func:`unicorn.metrics.mean_foreground_color` with ``interior=1``, then
:func:`unicorn.metrics.color_errors`: the mean error over the mean error of predicting the scored views' average
colour); the reconstruction error is the mean squared error of the model's own (soft) render against the image.

Each row refines all objects together (a batch; each object's refinement is independent of the others) and gives
the wall time and the process CPU time per object.

    python benchmarks/refine.py /work/runs/main0/checkpoints/last.ckpt --root <synthetic dataset folder>
    python benchmarks/refine.py CKPT --root ROOT --split val --cars 5 --steps 0,50 --parts all
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch

from unicorn.data import build_dataset
from unicorn.evaluation.rendering import hard_render
from unicorn.io import load_model
from unicorn.metrics import color_errors, evaluate_meshes, mask_iou, mean_foreground_color
from unicorn.model import Prediction, Unicorn
from unicorn.objectives.refine import PARTS, RefineOptions, RefineOptionsError, refine

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import comma_list, existing_file, existing_folder, non_negative_int, positive_int  # noqa: E402

#: the part sets of the default table: each part alone, all of them, and RefineOptions' default parts
PART_SETS = ("codes", "texture", "vertices", "pose", "all", "default")
#: the RefineOptions fields --set may change (its numbers)
SETTABLE = tuple(f.name for f in fields(RefineOptions) if f.type in (float, "float"))


def part_sets(text: str) -> list[str]:
    """An argparse ``type``: comma-separated part sets, each names of :data:`PARTS` joined by '+', 'all' or
    'default'."""
    sets = [s.strip() for s in text.split(",")]
    for s in sets:
        if s not in ("all", "default") and not all(name in PARTS for name in s.split("+")):
            raise argparse.ArgumentTypeError(
                f"unknown part set {s!r}: names of {list(PARTS)} joined by '+', 'all' or 'default'"
            )
    return sets


def setting(text: str) -> tuple[str, float]:
    """An argparse ``type``: ``NAME=VALUE``, a number field of :class:`RefineOptions` and a finite number."""
    name, sep, value = text.partition("=")
    if not sep or name.strip() not in SETTABLE:
        raise argparse.ArgumentTypeError(f"must be NAME=VALUE, NAME one of {', '.join(SETTABLE)}, got {text!r}")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"{name.strip()} must be a number, got {value!r}")
    return name.strip(), number


def icp_setting(text: str) -> tuple[int, int]:
    """An argparse ``type``: ``POINTS,ITERATIONS``, whole numbers >= 1 and >= 0."""
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"must be POINTS,ITERATIONS, got {text!r}")
    return positive_int(parts[0]), non_negative_int(parts[1])


def novel_view_poses(
    R_pred: torch.Tensor,
    T_pred: torch.Tensor,
    R_in: torch.Tensor,
    T_in: torch.Tensor,
    R_new: torch.Tensor,
    T_new: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the predicted object appears from a novel camera: the input placement moved by the known camera motion.

    The ground-truth cameras of one object map its points as ``x_view = x_gt @ R_v + T_v`` (view v). The camera
    motion from the input view to a novel view, in view coordinates, is therefore
    ``x_new = (x_in - T_in) @ R_in^T @ R_new + T_new``. The model placed its own object in the input view as
    ``x_in = x_pred @ R_pred + T_pred`` (its learnt object frame need not be the ground truth's); substituting,

        ``R = R_pred @ R_in^T @ R_new``,  ``T = (T_pred - T_in) @ R_in^T @ R_new + T_new``.

    Only the relative motion between the two ground-truth cameras is used: the pose learnt from the input view
    (refined or not) carries over, and an error in it shows in every novel view. With cameras that look at the
    object's centre from one distance (``T_in = T_new``) this is the predicted pose composed with the relative
    rotation ``R_in^T @ R_new``, plus the translation the rotation gives the predicted offset.

    Args:
        R_pred, T_pred: (N, 3, 3), (N, 3) the predicted (or refined) pose of the input view.
        R_in, T_in: (N, 3, 3), (N, 3) the input view's ground-truth camera.
        R_new, T_new: (N, 3, 3), (N, 3) the novel view's ground-truth camera.

    Returns:
        R (N, 3, 3), T (N, 3): the pose to render the predicted object with at the novel view.
    """
    M = R_in.transpose(-1, -2) @ R_new
    return R_pred @ M, ((T_pred - T_in).unsqueeze(-2) @ M).squeeze(-2) + T_new


def load_views(data: Any, cars: int) -> dict[str, Any]:
    """Every view of the first ``cars`` objects: images (N, V, 3, S, S), masks (N, V, 1, S, S), R (N, V, 3, 3),
    T (N, V, 3), the input view of each (N,), points and normals (N, P, 3)."""
    n_models, V = len(data.models), data.n_views
    cars = min(cars, n_models)
    images, masks, R, T, points, normals = [], [], [], [], [], []
    for m in range(cars):
        items = [data[v * n_models + m] for v in range(V)]
        images.append(torch.stack([it["image"] for it in items]))
        masks.append(torch.stack([it["mask"] for it in items]))
        R.append(torch.stack([it["R"] for it in items]))
        T.append(torch.stack([it["T"] for it in items]))
        p, n = data.load_points(m)
        points.append(p)
        normals.append(n)
    return {
        "images": torch.stack(images),
        "masks": torch.stack(masks).float(),
        "R": torch.stack(R),
        "T": torch.stack(T),
        "input": torch.as_tensor(data.random_views[:cars], dtype=torch.long),
        "points": torch.stack(points),
        "normals": torch.stack(normals),
    }


def view_scores(
    model: Unicorn,
    pred: Prediction,
    index: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    views: dict[str, Any],
    sel: tuple[torch.Tensor, torch.Tensor],
) -> dict[str, torch.Tensor]:
    """Reconstruction error, mask IoU and interior colours of predictions ``index`` (M,) rendered at poses R, T
    against the views ``sel = (object, view)`` (M,) each."""
    images, masks = views["images"][sel], views["masks"][sel]
    verts, tex = pred.verts[index], pred.texture[index]
    with torch.no_grad():
        rec, _ = model.render(verts, tex, R, T, None if pred.background is None else pred.background[index])
        hard = hard_render(model, verts, tex, R, T, images.shape[-1], 3).images
    return {
        "rec": (rec - images).square().flatten(1).mean(1),
        "iou": mask_iou(hard[:, 3:], masks, reduction="none"),
        "colour": mean_foreground_color(hard[:, :3], hard[:, 3:], interior=1),
        "gt_colour": mean_foreground_color(images, masks, interior=1),
    }


def colour_ratio(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean colour error over the mean error of the scored views' average colour (NaN rows left out)."""
    ok = ~(pred.isnan().any(1) | gt.isnan().any(1))
    err, base = color_errors(pred[ok].double(), gt[ok].double())
    return float(err.mean() / base.mean())


def score(
    model: Unicorn, pred: Prediction, views: dict[str, Any], icp: tuple[int, int], same_mesh: dict[str, float] | None
) -> dict[str, float]:
    """Input-view, novel-view and 3D scores of the refined predictions of every object (see the module docstring);
    ``same_mesh``: the 3D scores to reuse, when the mesh and pose are those already scored."""
    N, V = views["images"].shape[:2]
    objects = torch.arange(N)
    inp = views["input"]
    R_in, T_in = views["R"][objects, inp], views["T"][objects, inp]
    s_in = view_scores(model, pred, objects, pred.R, pred.T, views, (objects, inp))
    # every other view of every object
    obj, view = torch.meshgrid(objects, torch.arange(V), indexing="ij")
    keep = view != inp[:, None]
    obj, view = obj[keep], view[keep]
    R_new, T_new = novel_view_poses(
        pred.R[obj], pred.T[obj], R_in[obj], T_in[obj], views["R"][obj, view], views["T"][obj, view]
    )
    s_new = view_scores(model, pred, obj, R_new, T_new, views, (obj, view))
    if same_mesh is not None:
        cd = same_mesh
    else:
        mesh = evaluate_meshes(
            pred.verts,
            model.template.faces,
            views["points"],
            views["normals"],
            R_pred=pred.R,
            T_pred=pred.T,
            R_gt=R_in,
            T_gt=T_in,
            num_points=icp[0],
            icp_iterations=icp[1],
            workers=torch.get_num_threads(),
        )
        cd = {"CD": float(mesh["chamfer-L1"].mean()), "CD-ICP": float(mesh["chamfer-L1-ICP"].mean())}
    return {
        "input rec": float(s_in["rec"].mean()),
        "input IoU": float(s_in["iou"].mean()),
        "input colour": colour_ratio(s_in["colour"], s_in["gt_colour"]),
        "novel rec": float(s_new["rec"].mean()),
        "novel IoU": float(s_new["iou"].mean()),
        "novel colour": colour_ratio(s_new["colour"], s_new["gt_colour"]),
        **cd,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", type=existing_file)
    p.add_argument(
        "--root", type=existing_folder, required=True, help="the synthetic dataset folder (with metadata.yaml)"
    )
    p.add_argument("--split", default="test", choices=("train", "val", "test"))
    p.add_argument("--cars", type=positive_int, default=20, help="objects of the split (the first ones)")
    p.add_argument(
        "--steps", type=comma_list(non_negative_int), default=[0, 10, 50, 200], help="comma-separated step counts"
    )
    p.add_argument(
        "--parts",
        type=part_sets,
        default=list(PART_SETS),
        help=f"part sets: names of {list(PARTS)} joined by '+', 'all' or 'default' (RefineOptions' parts), "
        "comma-separated",
    )
    p.add_argument("--threads", type=positive_int, default=2, help="torch threads")
    p.add_argument(
        "--icp", type=icp_setting, default=(5000, 30), help="points sampled per mesh and ICP iterations of the Chamfer"
    )
    p.add_argument(
        "--set",
        type=setting,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a RefineOptions field for every row (repeatable), e.g. --set code_weight=0.1",
    )
    args = p.parse_args()
    overrides = dict(args.set)
    try:  # every row's options, before any work
        for steps in args.steps:
            RefineOptions(steps=steps, **overrides)
    except RefineOptionsError as err:
        p.error(f"--steps/--set: {err}")
    warnings.filterwarnings("ignore", message="some pixels had more than faces_per_pixel")
    torch.set_num_threads(args.threads)
    icp = args.icp

    model, info = load_model(args.checkpoint)
    data = build_dataset(
        "synthetic", args.split, args.root, img_size=model.config["image_size"], views="all", with_points=False
    )
    views = load_views(data, args.cars)
    N = views["images"].shape[0]
    inputs = views["images"][torch.arange(N), views["input"]]
    with torch.no_grad():
        initial = model.eval().predict(inputs)

    rows: list[tuple[str, str, float, float, dict[str, float]]] = []
    for steps in args.steps:
        for parts in args.parts if steps > 0 else ["-"]:
            if parts in ("default", "-"):
                options = RefineOptions(steps=steps, **overrides)
            else:
                names = tuple(PARTS) if parts == "all" else tuple(parts.split("+"))
                options = RefineOptions(steps=steps, parts=names, **overrides)
            wall, cpu = time.perf_counter(), time.process_time()
            result = refine(model, inputs, options, initial=initial)
            wall, cpu = (time.perf_counter() - wall) / N, (time.process_time() - cpu) / N
            p = result.prediction
            unmoved = all(torch.equal(getattr(p, k), getattr(initial, k)) for k in ("verts", "R", "T"))
            same = {k: rows[0][4][k] for k in ("CD", "CD-ICP")} if unmoved and rows else None
            rows.append((str(steps), parts, wall, cpu, score(model, p, views, icp, same)))
            print(steps, parts, f"{wall:.2f} s/img", {k: round(v, 4) for k, v in rows[-1][4].items()}, flush=True)

    cols = list(rows[0][4])
    print(
        f"\n{N} {args.split} objects, refined on one view each and scored on the other "
        f"{views['images'].shape[1] - 1}; {info.describe()}; {args.threads} threads; options "
        f"{RefineOptions(**overrides)}\n"
    )
    print("| steps | parts | s / image (wall) | CPU s / image | " + " | ".join(cols) + " |")
    print("|---|---|---|---|" + "---|" * len(cols))
    for steps, parts, wall, cpu, s in rows:
        print(f"| {steps} | {parts} | {wall:.2f} | {cpu:.2f} | " + " | ".join(f"{s[c]:.4f}" for c in cols) + " |")
    base = rows[0][4]
    print("\nnovel-view change against the prediction (colour ratio, IoU, CD-ICP):")
    for steps, parts, _, _, s in rows[1:]:
        print(
            f"  {steps} steps, {parts}: colour {100 * (s['novel colour'] / base['novel colour'] - 1):+.1f} %, "
            f"IoU {s['novel IoU'] - base['novel IoU']:+.4f}, CD-ICP {s['CD-ICP'] - base['CD-ICP']:+.4f}"
        )


if __name__ == "__main__":
    main()
