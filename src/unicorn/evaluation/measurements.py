"""The measurements of the evaluation loop: one small object per family of metrics, chosen from the protocol.

:func:`~unicorn.evaluation.evaluate` predicts and renders each batch once (an :class:`EvaluatedBatch`), then runs
the measurements that :func:`measurements_for` picks from the protocol's fields, in order. Each one adds per-image
scores to the batch (:attr:`EvaluatedBatch.scores`: they become the columns of its rows, in the order added) or
records what the set-level metrics need in the :class:`~unicorn.evaluation.tables.Accumulator`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
import torch.nn.functional as F

from unicorn.checks import check_shape
from unicorn.evaluation.interface import EvaluableModel
from unicorn.evaluation.protocols import COLOR_INTERIOR, EvalOptions
from unicorn.evaluation.protocols import Protocol as EvalProtocol
from unicorn.evaluation.rendering import hard_render, vertex_visibility
from unicorn.evaluation.tables import Accumulator, ShapeEntry, object_samples
from unicorn.metrics import NearestNeighborIndex, evaluate_meshes, mask_iou, mean_foreground_color
from unicorn.model import Prediction
from unicorn.render import RenderOutput

__all__ = [
    "CandidateRecords",
    "EvaluatedBatch",
    "KeypointRecords",
    "MaskScores",
    "Measurement",
    "MeshScores",
    "OwnMeanScores",
    "PoseRecords",
    "ShapeBaselineScores",
    "ShapeRetrievalRecords",
    "measurements_for",
]


@dataclass
class EvaluatedBatch:
    """One batch as the loop predicted and rendered it, and the per-image scores measured on it so far.

    Attributes:
        batch: the collated items (``image``, ``mask``, ``R``/``T``, ``points``... as :mod:`unicorn.data` yields).
        images: (B, 3, S, S) the inputs at the model's size S.
        pred: the model's prediction for them.
        R: (B, 3, 3); T: (B, 3) the pose everything is rendered and aligned with (the prediction's, or the
            ground truth's with ``oracle_pose``).
        rec: (B, 3, S, S) the model's soft reconstruction.
        hard: the hard render at ``mask_size``: ``images`` (B, 4, M, M), RGB then each pixel's coverage.
        mask_size: M, the side of the ground-truth masks (S when the batch has none).
        has_mask: every item has a ground-truth mask.
        groups: each image's group name.
        first_row: the row number its first image will have.
        scores: per-image scores by column name, each (B,).
        labels: per-image integer labels by column name (the selected pose candidate), placed before the scores.
        gt_index: the search structure over the ground-truth points (:func:`_gt_indices`), once built.
    """

    batch: Mapping[str, Any]
    images: torch.Tensor
    pred: Prediction
    R: torch.Tensor
    T: torch.Tensor
    rec: torch.Tensor
    hard: RenderOutput
    mask_size: int
    has_mask: bool
    groups: list[str]
    first_row: int
    scores: dict[str, torch.Tensor] = field(default_factory=dict)
    labels: dict[str, list[int]] = field(default_factory=dict)
    gt_index: NearestNeighborIndex | list[NearestNeighborIndex] | None = None

    @property
    def alpha(self) -> torch.Tensor:
        """(B, 1, M, M) each pixel's coverage by the hard render (mask_iou's silhouette: more than half)."""
        return self.hard.images[:, 3:]

    @property
    def has_pose(self) -> bool:
        """Every item has a ground-truth pose."""
        has_pose = self.batch.get("has_pose")
        return isinstance(has_pose, torch.Tensor) and bool(has_pose.all())


class Measurement(Protocol):
    """One family of metrics: scores a batch into ``view.scores`` and / or records into ``acc``."""

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None: ...


class MaskScores:
    """``mask-iou`` against the ground-truth masks, and each image's mean foreground colours (for ``color-err``)."""

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        if not view.has_mask:
            return
        gt_mask = view.batch["mask"].to(view.images.device)
        view.scores["mask-iou"] = mask_iou(view.alpha, gt_mask, reduction="none")
        # mean foreground colours: the input's inside its mask, the reconstruction's inside its silhouette,
        # both without the one-input-pixel border where colours mix with the background (COLOR_INTERIOR)
        B, size = view.images.shape[0], view.images.shape[-1]
        small_mask = F.interpolate(gt_mask.float().reshape(B, 1, *gt_mask.shape[-2:]), size=(size, size))
        r_hard = COLOR_INTERIOR * max(1, round(view.mask_size / size))
        ours = mean_foreground_color(view.hard.images[:, :3], view.alpha, interior=r_hard)
        theirs = mean_foreground_color(view.images, small_mask, interior=COLOR_INTERIOR)
        # the same over the pixels both silhouettes cover: the texture's error alone, without what the
        # reconstruction paints outside the object (e.g. an open chair back a genus-0 mesh cannot open)
        both = ((view.alpha >= 0.5) & (gt_mask.reshape(view.alpha.shape) >= 0.5)).float()
        ours_both = mean_foreground_color(view.hard.images[:, :3], both, interior=r_hard)
        small_both = F.interpolate(both, size=(size, size))
        theirs_both = mean_foreground_color(view.images, small_both, interior=COLOR_INTERIOR)
        for i, g in enumerate(view.groups):
            row = view.first_row + i
            acc.colors[""].setdefault(g, []).append((row, ours[i].cpu(), theirs[i].cpu()))
            acc.colors["-overlap"].setdefault(g, []).append((row, ours_both[i].cpu(), theirs_both[i].cpu()))


class MeshScores:
    """The predicted meshes against the ground-truth points (:func:`~unicorn.metrics.evaluate_meshes`).

    ``posed``: with the ground-truth pose and after ICP; otherwise (no ground-truth pose) only the ICP-registered
    numbers, the only meaningful ones, are computed.
    """

    def __init__(self, model: EvaluableModel, options: EvalOptions, posed: bool) -> None:
        self.model, self.options, self.posed = model, options, posed

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        if "points" not in view.batch:
            return
        view.gt_index = _gt_indices(view.batch, view.images.device, view.pred.verts.dtype, self.options)
        mesh = _mesh_scores(self.model, view.pred.verts, view, self.options, self.posed, run_direct=self.posed)
        if not self.posed:
            mesh = {k: v for k, v in mesh.items() if k.endswith("-ICP")}
        view.scores.update(mesh)


class ShapeBaselineScores:
    """A fixed mesh, e.g. the mean training shape of the object's category, scored on every object after ICP
    beside the model: ``chamfer-L1-ICP-mean-shape`` and ``shape-win``.

    Args:
        verts: (V, 3) one mesh for every image, or group name -> (V, 3) each group's mesh.
    """

    def __init__(
        self, model: EvaluableModel, options: EvalOptions, verts: torch.Tensor | Mapping[str, torch.Tensor]
    ) -> None:
        self.model, self.options, self.verts = model, options, verts

    def _batch_verts(self, groups: list[str]) -> torch.Tensor:
        """(B, V, 3) each image's baseline mesh."""
        if isinstance(self.verts, torch.Tensor):
            meshes = [self.verts] * len(groups)
        else:
            missing = sorted({g for g in groups if g not in self.verts})
            if missing:
                raise ValueError(
                    f"shape_baseline has no mesh for the evaluated group(s) {missing}; it has {sorted(self.verts)}"
                )
            meshes = [self.verts[g] for g in groups]
        if all(m is meshes[0] for m in meshes):  # one mesh: the same expanded tensor for every image
            return meshes[0].unsqueeze(0).expand(len(groups), -1, -1)
        return torch.stack(meshes)

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        if "chamfer-L1-ICP" not in view.scores:
            return
        verts = self._batch_verts(view.groups)
        base = _mesh_scores(self.model, verts, view, self.options, False, run_direct=False)["chamfer-L1-ICP"]
        view.scores["chamfer-L1-ICP-mean-shape"] = base
        view.scores["shape-win"] = _wins(view.scores["chamfer-L1-ICP"], base)


class OwnMeanScores:
    """The model's own average mesh of each group (``means``: group -> (V, 3)) at each image's pose and alignment:
    ``chamfer-L1-ICP-own-mean`` and ``shape-win-own``."""

    def __init__(
        self, model: EvaluableModel, options: EvalOptions, posed: bool, means: Mapping[str, torch.Tensor]
    ) -> None:
        self.model, self.options, self.posed, self.means = model, options, posed, means

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        if "chamfer-L1-ICP" not in view.scores:
            return
        # the same pose and alignment as the model's prediction: only the shape differs
        verts = torch.stack([self.means[g] for g in view.groups])
        own = _mesh_scores(self.model, verts, view, self.options, self.posed, run_direct=False)["chamfer-L1-ICP"]
        view.scores["chamfer-L1-ICP-own-mean"] = own
        view.scores["shape-win-own"] = _wins(view.scores["chamfer-L1-ICP"], own)


class ShapeRetrievalRecords:
    """Records each image's shapes and its object's ground-truth samples for the shape retrieval
    (:func:`~unicorn.evaluation.tables.shape_scores`): needs ground-truth points and poses and each item's object."""

    def __init__(self, options: EvalOptions) -> None:
        self.options = options

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        batch, pred = view.batch, view.pred
        if not (isinstance(batch.get("model"), torch.Tensor) and "points" in batch and view.has_pose):
            return
        for i, g in enumerate(view.groups):
            obj = int(batch["model"][i])
            objects = acc.objects.setdefault(g, {})
            if obj not in objects:
                objects[obj] = object_samples(batch["points"][i], self.options.shape_points, self.options.seed + obj)
            entry = ShapeEntry(
                view.first_row + i,
                obj,
                pred.verts[i].cpu(),
                pred.canonical_verts[i].cpu(),
                pred.scale[i].cpu(),
                view.R[i].cpu(),
                view.T[i].cpu(),
                batch["R"][i].cpu(),
            )
            acc.shapes.setdefault(g, []).append(entry)


class PoseRecords:
    """Records the selected, every candidate's and the ground-truth rotations for the pose errors (after the
    canonical-frame alignment)."""

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        if not bool(view.batch["has_pose"].all()):
            return
        for i, g in enumerate(view.groups):
            R_all = view.pred.poses.R[:, i].cpu()  # (K, 3, 3) every candidate
            record = (view.first_row + i, view.pred.R[i].cpu(), view.batch["R"][i].cpu(), R_all)
            acc.poses.setdefault(g, []).append(record)


class CandidateRecords:
    """Each image's selected pose candidate (argmax of ``pred.poses.probs``, (K, B)): the ``candidate`` column,
    and the per-group candidate shares."""

    def __init__(self, n_candidates: int) -> None:
        self.n_candidates = n_candidates

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        acc.n_candidates = self.n_candidates
        chosen = view.pred.poses.probs.argmax(0).tolist()  # (B,) selected candidates
        view.labels["candidate"] = [int(c) for c in chosen]
        for i, g in enumerate(view.groups):
            acc.candidates.setdefault(g, []).append(int(chosen[i]))


class KeypointRecords:
    """Records each image's mesh, pose, visible vertices and keypoints for PCK by keypoint transfer."""

    def __init__(self, model: EvaluableModel, options: EvalOptions) -> None:
        self.model, self.options = model, options

    def __call__(self, view: EvaluatedBatch, acc: Accumulator) -> None:
        keypoints = view.batch.get("keypoints")
        if not isinstance(keypoints, torch.Tensor):
            return
        pred, options = view.pred, self.options
        seen = view.hard
        if options.visibility_supersample != options.mask_supersample:
            seen = hard_render(
                self.model, pred.verts, pred.texture, view.R, view.T, view.mask_size, options.visibility_supersample
            )
        visible = vertex_visibility(seen.face_ids, self.model.template.faces, pred.verts.shape[1])
        for i, g in enumerate(view.groups):
            acc.keypoint_frames[g] = int(view.mask_size)
            acc.keypoints.setdefault(g, []).append(
                (pred.verts[i].cpu(), pred.R[i].cpu(), pred.T[i].cpu(), visible[i].cpu(), keypoints[i])
            )


def measurements_for(
    protocol: EvalProtocol,
    options: EvalOptions,
    model: EvaluableModel,
    shape_baseline: torch.Tensor | Mapping[str, torch.Tensor] | None = None,
    own_means: Mapping[str, torch.Tensor] | None = None,
) -> list[Measurement]:
    """The measurements a protocol makes, in the order their columns appear in a row.

    Args:
        protocol: what the dataset provides (:class:`~unicorn.evaluation.protocols.Protocol`).
        options: the evaluation's settings.
        model: the evaluated model.
        shape_baseline: (V, 3) a mesh, or group name -> (V, 3) each group's mesh, scored beside the model on every
            object (:class:`ShapeBaselineScores`).
        own_means: per group, the model's average mesh (V, 3) (:class:`OwnMeanScores`).
    """
    steps: list[Measurement] = []
    if protocol.masks:
        steps.append(MaskScores())
    if protocol.meshes is not None:
        posed = protocol.meshes == "posed"
        steps.append(MeshScores(model, options, posed))
        if shape_baseline is not None:
            steps.append(ShapeBaselineScores(model, options, shape_baseline))
        if own_means is not None:
            steps.append(OwnMeanScores(model, options, posed, own_means))
        if posed and options.shape_points > 0:
            steps.append(ShapeRetrievalRecords(options))
    # with the oracle pose every image is rendered at its ground-truth pose: no pose error, no candidate selected
    if protocol.poses and not options.oracle_pose:
        steps.append(PoseRecords())
    if model.n_candidates > 1 and not options.oracle_pose:
        steps.append(CandidateRecords(model.n_candidates))
    if protocol.keypoints:
        steps.append(KeypointRecords(model, options))
    return steps


def checked_shape_baseline(
    shape_baseline: torch.Tensor | Mapping[str, torch.Tensor], model: EvaluableModel, device: torch.device
) -> torch.Tensor | dict[str, torch.Tensor]:
    """``shape_baseline``, one (V, 3) mesh or group name -> (V, 3) mesh, as meshes on the model's template
    topology, on ``device`` in its dtype.

    Raises:
        ShapeError: a mesh is not (V, 3) with the template's V.
    """
    dims = {"V": model.template.num_verts}
    dtype = model.template.verts.dtype
    if isinstance(shape_baseline, torch.Tensor):
        check_shape(shape_baseline, "V, 3", "shape_baseline", dims)
        return shape_baseline.to(device=device, dtype=dtype)
    for group, verts in shape_baseline.items():
        check_shape(verts, "V, 3", f"shape_baseline[{group!r}]", dims)
    return {group: verts.to(device=device, dtype=dtype) for group, verts in shape_baseline.items()}


def _mesh_scores(
    model: EvaluableModel,
    pred_verts: torch.Tensor,
    view: EvaluatedBatch,
    options: EvalOptions,
    with_pose: bool,
    run_direct: bool = True,
) -> dict[str, torch.Tensor]:
    """:func:`evaluate_meshes` of ``pred_verts`` (B, V, 3) on the batch's ground truth (``view.gt_index``, shared
    by the scorings of several meshes on it), placed with ``view.R`` / ``view.T``; ragged ground truths are scored
    one image at a time."""
    faces, batch, device = model.template.faces, view.batch, view.images.device
    kwargs = dict(
        num_points=options.num_points,
        run_direct=run_direct,
        run_icp=options.icp_iterations > 0,
        icp_iterations=max(options.icp_iterations, 1),
        seed=options.seed,
    )
    normals = batch.get("normals")
    gt_index = view.gt_index
    if isinstance(gt_index, NearestNeighborIndex):
        pose = {}
        if with_pose:
            pose = dict(R_pred=view.R, T_pred=view.T, R_gt=batch["R"].to(device), T_gt=batch["T"].to(device))
        n = None if normals is None else normals.to(device)
        return evaluate_meshes(pred_verts, faces, gt_index.y, n, **pose, **kwargs, gt_index=gt_index)
    assert gt_index is not None
    per: list[dict[str, torch.Tensor]] = []
    for i, index in enumerate(gt_index):
        pose = {}
        if with_pose:
            pose = dict(
                R_pred=view.R[i : i + 1],
                T_pred=view.T[i : i + 1],
                R_gt=batch["R"][i : i + 1].to(device),
                T_gt=batch["T"][i : i + 1].to(device),
            )
        n_i = None if normals is None else normals[i][None].to(device)
        per.append(evaluate_meshes(pred_verts[i : i + 1], faces, index.y, n_i, **pose, **kwargs, gt_index=index))
    return {k: torch.cat([p[k] for p in per]) for k in per[0]}


def _gt_indices(
    batch: Mapping[str, Any], device: torch.device, dtype: torch.dtype, options: EvalOptions
) -> NearestNeighborIndex | list[NearestNeighborIndex]:
    """The search structure over the batch's ground-truth points (one per image when they are ragged), built
    once for the scorings of the model and of the baselines."""
    workers = torch.get_num_threads() if options.nn_workers is None else options.nn_workers
    points = batch["points"]
    if isinstance(points, torch.Tensor):
        return NearestNeighborIndex(points.to(device=device, dtype=dtype), workers=workers)
    return [NearestNeighborIndex(p[None].to(device=device, dtype=dtype), workers=workers) for p in points]


def _wins(ours: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
    """(B,) 1 where ``ours`` is the lower error, 0.5 on a tie, else 0."""
    return (ours < base).to(ours.dtype) + 0.5 * (ours == base).to(ours.dtype)
