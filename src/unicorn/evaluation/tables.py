"""What an evaluation collects per image and how it sums it up: colour errors, shape retrieval, per-group tables,
set metrics.

:func:`unicorn.evaluation.evaluate` fills an :class:`Accumulator` batch by batch, then :func:`color_scores`,
:func:`shape_scores` and :func:`summary_table` turn it into the per-image rows and the per-group table (pose
errors after the canonical-frame alignment, PCK by keypoint transfer, pose-candidate usage, colour ratio, shape
spread ratio).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from unicorn.evaluation.interface import EvaluableModel
from unicorn.evaluation.protocols import COLOR_SUFFIXES, METRIC_ORDER, ROW_INFO, EvalOptions
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.metrics import (
    align_canonical_frame,
    color_errors,
    geodesic_error,
    keypoint_transfer_pck,
    pose_errors,
    rotation_accuracy,
    sample_points_from_meshes,
    shape_retrieval,
    shape_spread,
)

__all__ = ["Accumulator", "ShapeEntry", "candidate_shares", "color_scores", "shape_scores", "summary_table"]


@dataclass(frozen=True)
class ShapeEntry:
    """What the shape retrieval keeps of one image (CPU tensors).

    Attributes:
        row: the image's row number.
        obj: which object the image shows (unique within its group).
        verts: (V, 3) the predicted object-frame mesh; canonical: (V, 3) its canonical mesh (before the
            scale); scale: (3,) its anisotropic scale.
        R: (3, 3); T: (3,) the pose it is placed with (the predicted one, or the ground truth's with
            ``oracle_pose``).
        R_gt: (3, 3) the image's ground-truth rotation.
    """

    row: int
    obj: int
    verts: torch.Tensor
    canonical: torch.Tensor
    scale: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    R_gt: torch.Tensor


class Accumulator:
    """Per-image rows plus what the set-level metrics need, grouped."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []
        # (row, R_pred (3, 3), R_gt (3, 3), every candidate's R (K, 3, 3))
        self.poses: dict[str, list[tuple[int, torch.Tensor, torch.Tensor, torch.Tensor]]] = {}
        self.keypoints: dict[str, list[tuple[torch.Tensor, ...]]] = {}
        # side of the keypoint frame per group (the ground-truth mask side, 256 for CUB's evaluation items)
        self.keypoint_frames: dict[str, int] = {}
        # selected pose-candidate index per image, grouped, and the number K of candidates (0: not recorded)
        self.candidates: dict[str, list[int]] = {}
        self.n_candidates = 0
        # per column suffix ("": each inside its own silhouette; "-overlap": both inside the pixels both
        # silhouettes cover), per group: (row number, reconstruction's mean foreground colour (3,), input's (3,))
        self.colors: dict[str, dict[str, list[tuple[int, torch.Tensor, torch.Tensor]]]] = {
            suffix: {} for suffix in COLOR_SUFFIXES
        }
        # shape retrieval, per group: each image's entry, and each object's ground-truth points, (2 n, 3): the
        # candidates' n then the ceiling's n (two independent samples of its surface)
        self.shapes: dict[str, list[ShapeEntry]] = {}
        self.objects: dict[str, dict[int, torch.Tensor]] = {}
        self.spread_ratio: dict[str, dict[str, float]] = {}  # group -> shape-spread-ratio, shape-detail-ratio


def candidate_shares(chosen: Sequence[int], n_candidates: int) -> list[float]:
    """Fraction of the images that selected each of the K pose candidates.

    Args:
        chosen: the selected candidate index of each image, in [0, K).
        n_candidates: K.

    Returns:
        K fractions summing to 1 (a candidate never chosen gets 0).

    Example:
        >>> candidate_shares([0, 0, 2, 0], 4)
        [0.75, 0.0, 0.25, 0.0]
    """
    if n_candidates < 1:
        raise ValueError(f"need at least one candidate, got n_candidates={n_candidates}")
    if len(chosen) == 0:
        raise ValueError("no images: candidate shares are undefined")
    idx = torch.as_tensor(list(chosen), dtype=torch.long)
    if int(idx.min()) < 0 or int(idx.max()) >= n_candidates:
        raise ValueError(f"candidate indices must be in [0, {n_candidates}), got {sorted(set(idx.tolist()))}")
    counts = torch.bincount(idx, minlength=n_candidates).double()
    return (counts / counts.sum()).tolist()


def color_scores(acc: Accumulator) -> None:
    """Per-image ``color-err`` and ``color-err-mean`` (the group's average input colour as the prediction), and
    the same over the pixels both silhouettes cover, ``color-err-overlap`` and ``color-err-mean-overlap``."""
    for suffix, groups in acc.colors.items():
        for entries in groups.values():
            rows, pred, gt = zip(*entries)
            pred_colors, gt_colors = torch.stack(pred).double(), torch.stack(gt).double()
            if bool(torch.isnan(gt_colors).any(dim=1).all()):
                continue  # no input foreground at all: nothing to compare
            model, base = color_errors(pred_colors, gt_colors)
            for r, m, b in zip(rows, model.tolist(), base.tolist()):
                acc.rows[r][f"color-err{suffix}"], acc.rows[r][f"color-err-mean{suffix}"] = m, b


def object_samples(points: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """Two disjoint random subsets of a ground-truth cloud, ``(2 n', 3)`` with ``n' = min(n, P // 2)``: the first
    half stands for the object among the candidates, the second for its ground truth as a reconstruction."""
    k = min(n, points.shape[0] // 2)
    if k < 1:
        raise ValueError(f"a ground-truth cloud of {points.shape[0]} points cannot give two samples")
    keep = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(seed))[: 2 * k]
    return points[keep]


def _sample(verts: torch.Tensor, faces: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """(B, n, 3) points on each mesh, every mesh with the same random numbers (one shape repeated: one cloud)."""
    return torch.stack([sample_points_from_meshes(v, faces, n, seed=seed)[0] for v in verts])


def shape_scores(acc: Accumulator, faces: torch.Tensor, options: EvalOptions) -> None:
    """Per-image shape retrieval among the group's objects and the group's shape spread ratio.

    Per image ``shape-top1``, ``shape-top3``, ``shape-mrr`` (its reciprocal rank; the group mean is the MRR) of
    :func:`~unicorn.metrics.shape_retrieval` for three reconstructions placed at the image's pose: the model's
    (``shape-*``), an independent sample of the ground truth (``shape-*-gt``, the ceiling) and the model's mean
    canonical mesh over the group's images times the image's scale (``shape-*-floor``, the scale-only
    predictor). Per group with ``options.shape_spread``, in :attr:`Accumulator.spread_ratio`: the predicted meshes'
    :func:`~unicorn.metrics.shape_spread` over the ground truth's, ``shape-spread-ratio`` (proportions count) and
    ``shape-detail-ratio`` (each axis normalised: the predicted meshes in their canonical frame, whose axes the
    anisotropic scale stretches, the ground truths in their object frame). A group of one object is left out
    (nothing to tell it from).
    """
    n, seed = options.shape_points, options.seed
    workers = torch.get_num_threads() if options.nn_workers is None else options.nn_workers
    for group, entries in acc.shapes.items():
        objects = acc.objects[group]
        ids = sorted(objects)
        if len(ids) < 2:
            continue
        k = min(x.shape[0] for x in objects.values()) // 2
        candidates = torch.stack([objects[i][:k] for i in ids]).double()  # (C, k, 3)
        ceiling = torch.stack([objects[i][k : 2 * k] for i in ids]).double()
        targets = torch.tensor([ids.index(e.obj) for e in entries])
        R, T, R_gt = (torch.stack([getattr(e, a) for e in entries]).double() for a in ("R", "T", "R_gt"))
        verts = torch.stack([e.verts for e in entries]).double()
        mean_canonical = torch.stack([e.canonical for e in entries]).double().mean(dim=0)
        floor = mean_canonical * torch.stack([e.scale for e in entries]).double()[:, None]
        faces_ = faces.cpu()
        own = _sample(verts, faces_, n, seed)  # (Q, n, 3) in the object frame
        queries = {
            "": own @ R + T[:, None],
            "-gt": ceiling[targets] @ R_gt,  # the object seen in the image's view (T: taken out by centring)
            "-floor": _sample(floor, faces_, n, seed) @ R + T[:, None],
        }
        for suffix, points in queries.items():
            got = shape_retrieval(points, R_gt, candidates, targets, workers=workers)
            for i, e in enumerate(entries):
                row = acc.rows[e.row]
                row[f"shape-top1{suffix}"] = float(got["top1"][i])
                row[f"shape-top3{suffix}"] = float(got["top3"][i])
                row[f"shape-mrr{suffix}"] = float(got["rr"][i])
        if not options.shape_spread:
            continue
        image_objects = torch.tensor([e.obj for e in entries])
        # the detail: the canonical meshes (one canonical mesh at any scale: one cloud, no spread)
        canonical = _sample(torch.stack([e.canonical for e in entries]).double(), faces_, n, seed)
        ratios = {}
        for name, predicted, per_axis in (("shape-spread-ratio", own, False), ("shape-detail-ratio", canonical, True)):
            truth = shape_spread(candidates[targets], image_objects, per_axis, workers=workers)
            ratios[name] = shape_spread(predicted, image_objects, per_axis, workers=workers) / truth
        acc.spread_ratio[group] = ratios


def _set_metrics(
    acc: Accumulator,
    group: str,
    model: EvaluableModel,
    options: EvalOptions,
    shares: Mapping[str, list[float]],
) -> dict[str, float]:
    """Metrics over all images of a group: pose errors (ShapeNet), PCK (CUB) and the pose-candidate usage."""
    out: dict[str, float] = {}
    if group in shares:
        out["cand-share-min"], out["cand-share-max"] = min(shares[group]), max(shares[group])
    for suffix in COLOR_SUFFIXES:
        err, err_mean = f"color-err{suffix}", f"color-err-mean{suffix}"
        errors = [(r[err], r[err_mean]) for r in acc.rows if r["group"] == group and err in r]
        errors = [(m, b) for m, b in errors if not (math.isnan(m) or math.isnan(b))]
        if errors:
            model_mean, base_mean = (float(np.mean(x)) for x in zip(*errors))
            out[f"color-ratio{suffix}"] = model_mean / base_mean if base_mean > 0 else float("nan")
    if group in acc.spread_ratio:
        out.update(acc.spread_ratio[group])
    if group in acc.poses:
        rows, R_pred, R_gt, R_all = zip(*acc.poses[group])
        R_pred, R_gt, R_all = torch.stack(R_pred), torch.stack(R_gt), torch.stack(R_all)  # R_all (N, K, 3, 3)
        if options.align_pose and len(rows) < 2:
            # the rotation aligning one image makes its error 0 whatever the prediction: the errors are undefined
            out.update(dict.fromkeys(pose_errors(R_pred, R_gt), math.nan))
            if R_all.shape[1] > 1:
                out["rot-acc-30-any"] = math.nan
        else:
            if options.align_pose:  # once, for the summary and the per-image errors
                Q = align_canonical_frame(R_pred, R_gt).to(R_pred)
                R_pred, R_all = Q @ R_pred, Q @ R_all
            out.update(pose_errors(R_pred, R_gt))
            if R_all.shape[1] > 1:  # the best of the candidates: what a perfect choice among them would score
                best = geodesic_error(R_all, R_gt.unsqueeze(1)).min(1).values
                out["rot-acc-30-any"] = rotation_accuracy(best, 30.0)
            for r, err in zip(rows, geodesic_error(R_pred, R_gt).tolist()):
                acc.rows[r]["rot-err"] = err
    kps = acc.keypoints.get(group, [])
    if len(kps) >= 2:
        verts, R, T, visible, keypoints = (torch.stack(x) for x in zip(*kps))
        scores = keypoint_transfer_pck(
            verts,
            R,
            T,
            visible,
            keypoints,
            image_size=acc.keypoint_frames[group],
            # a CPU copy: the collected meshes are on the CPU, and the model's own camera must stay where it is
            camera=PerspectiveCamera(focal_length=float(model.renderer.camera.focal_length)),
            num_pairs=options.num_pairs,
        )
        out.update({k: v for k, v in scores.items() if k.startswith("pck-")})
    return out


def summary_table(
    acc: Accumulator, model: EvaluableModel, options: EvalOptions, shares: Mapping[str, list[float]]
) -> tuple[list[dict[str, Any]], list[str]]:
    """Per-group means of the per-image metrics plus the group's set metrics; then the mean over groups."""
    groups = list(dict.fromkeys(row["group"] for row in acc.rows))
    rows: list[dict[str, Any]] = []
    for g in groups:
        members = [r for r in acc.rows if r["group"] == g]
        row: dict[str, Any] = {"group": g, "n-images": len(members)}
        keys = list(dict.fromkeys(k for r in members for k in r if k not in ROW_INFO))  # not the candidate index
        for k in keys:
            values = [r[k] for r in members if k in r and not math.isnan(r[k])]
            row[k] = float(np.mean(values)) if values else float("nan")
        row.update(_set_metrics(acc, g, model, options, shares))
        rows.append(row)
    present = {k for r in rows for k in r} - {"group", "n-images"}
    columns = [k for k in METRIC_ORDER if k in present] + sorted(present - set(METRIC_ORDER))
    rows = [{"group": r["group"], "n-images": r["n-images"], **{k: r[k] for k in columns if k in r}} for r in rows]
    mean: dict[str, Any] = {"group": "mean", "n-images": sum(r["n-images"] for r in rows)}
    for k in columns:
        values = [r[k] for r in rows if k in r and not math.isnan(r[k])]
        mean[k] = float(np.mean(values)) if values else float("nan")
    return rows + [mean], columns
