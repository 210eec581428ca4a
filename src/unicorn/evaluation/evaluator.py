"""The evaluation loop: a model and a dataset in, per-image scores, a per-group table and report samples out.

What each protocol scores is :mod:`unicorn.evaluation.protocols` (its docstring describes every metric); this
module builds the evaluation items of a dataset and runs the loop.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset, Subset
from tqdm.auto import tqdm

from unicorn.data import build_dataset
from unicorn.data.registry import dataset_spec
from unicorn.evaluation.interface import EvaluableModel, spread_indices
from unicorn.evaluation.protocols import (
    COLOR_INTERIOR,
    EvalOptions,
    EvaluationResult,
    Protocol,
    Sample,
    get_protocol,
)
from unicorn.evaluation.rendering import hard_render, vertex_visibility
from unicorn.evaluation.tables import (
    Accumulator,
    ShapeEntry,
    candidate_shares,
    color_scores,
    object_samples,
    shape_scores,
    summary_table,
)
from unicorn.metrics import (
    NearestNeighborIndex,
    evaluate_meshes,
    mask_iou,
    mean_foreground_color,
)

__all__ = ["build_eval_dataset", "candidate_shares", "collate", "evaluate", "group_namer"]


def build_eval_dataset(
    name: str,
    root: str,
    split: str = "test",
    img_size: int = 64,
    categories: str | list[str] | None = None,
    max_images: int | None = None,
    seed: int = 0,
) -> Dataset:
    """The evaluation items of a dataset, as its protocol needs them.

    ShapeNet / synthetic: one fixed random view per model (``seed``) with the ground-truth point clouds; CUB:
    masks and keypoints at 256 px (UNICORN's keypoint frame); Pascal3D+: the test split with the CAD clouds.
    With ``max_images``, that many items spread evenly over the split (so every category is represented).

    Args:
        name: a dataset name of :data:`PROTOCOLS`.
        root: its root folder (for ``synthetic``, the generated dataset, which holds ``metadata.yaml``).
        split: ``"train"``, ``"val"`` or ``"test"``.
        img_size: the model's input side (ShapeNet images keep their size and are resized in :func:`evaluate`).
        categories: ShapeNet / synthetic categories (names or synsets), None for all.
        max_images: evaluate at most this many items.
        seed: the view choice of ShapeNet.
    """
    options = dict(dataset_spec(name).eval_options)
    dataset = build_dataset(name, split, root, img_size=img_size, categories=categories, seed=seed, **options)
    if split == "train":
        # evaluation items are never augmented (ShapeNet training items are every view, which is fine)
        for attr in ("augment",):
            if hasattr(dataset, attr):
                setattr(dataset, attr, False)
    indices = spread_indices(len(dataset), max_images)
    return dataset if len(indices) == len(dataset) else Subset(dataset, indices)


def collate(items: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Stack tensors of equal shape; keep lists where they differ (e.g. CAD point clouds of different sizes)."""
    out: dict[str, Any] = {}
    for key in items[0]:
        values = [item[key] for item in items]
        if all(isinstance(v, torch.Tensor) for v in values) and len({tuple(v.shape) for v in values}) == 1:
            out[key] = torch.stack(values)
        else:
            out[key] = values
    return out


def _base_dataset(dataset: Dataset) -> Dataset:
    while isinstance(dataset, Subset):
        dataset = dataset.dataset
    return dataset


def group_namer(dataset: Dataset, dataset_name: str) -> Callable[[Mapping[str, Any], int], str]:
    """A function ``(batch, i) -> group name``: the ShapeNet category name, else the dataset name."""
    base = _base_dataset(dataset)
    synsets = getattr(base, "synsets", None)
    metadata = getattr(base, "metadata", None)
    if synsets is None or metadata is None:
        return lambda batch, i: dataset_name
    names = [metadata[s]["name"].split(",")[0] or s for s in synsets]
    return lambda batch, i: names[int(batch["category"][i])]


def _resize_images(images: torch.Tensor, size: int) -> torch.Tensor:
    if images.shape[-1] == size and images.shape[-2] == size:
        return images
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False, antialias=True).clamp(0, 1)


def _mesh_scores(
    model: EvaluableModel,
    pred_verts: torch.Tensor,
    batch: Mapping[str, Any],
    device: torch.device,
    options: EvalOptions,
    with_pose: bool,
    R_pred: torch.Tensor,
    T_pred: torch.Tensor,
    gt_index: NearestNeighborIndex | list[NearestNeighborIndex],
    run_direct: bool = True,
) -> dict[str, torch.Tensor]:
    """:func:`evaluate_meshes` on a batch; ragged ground truths are scored one image at a time.

    ``gt_index``: :func:`_gt_indices` of the batch, shared by the scorings of several meshes on it.
    """
    faces = model.template.faces
    kwargs = dict(
        num_points=options.num_points,
        run_direct=run_direct,
        run_icp=options.icp_iterations > 0,
        icp_iterations=max(options.icp_iterations, 1),
        seed=options.seed,
    )
    points, normals = batch["points"], batch.get("normals")
    if isinstance(points, torch.Tensor):
        assert isinstance(gt_index, NearestNeighborIndex)
        pose = {}
        if with_pose:
            pose = dict(R_pred=R_pred, T_pred=T_pred, R_gt=batch["R"].to(device), T_gt=batch["T"].to(device))
        return evaluate_meshes(
            pred_verts,
            faces,
            gt_index.y,
            None if normals is None else normals.to(device),
            **pose,
            **kwargs,
            gt_index=gt_index,
        )
    per: list[dict[str, torch.Tensor]] = []
    for i in range(pred_verts.shape[0]):
        pose = {}
        if with_pose:
            pose = dict(
                R_pred=R_pred[i : i + 1],
                T_pred=T_pred[i : i + 1],
                R_gt=batch["R"][i : i + 1].to(device),
                T_gt=batch["T"][i : i + 1].to(device),
            )
        n_i = None if normals is None else normals[i][None].to(device)
        index = gt_index[i]
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


def _require_poses(batch: Mapping[str, Any]) -> None:
    """Raise unless every item of the batch has a ground-truth pose (what ``oracle_pose`` substitutes)."""
    has_pose = batch.get("has_pose")
    if not isinstance(has_pose, torch.Tensor) or "R" not in batch or "T" not in batch:
        raise ValueError("oracle_pose needs ground-truth poses, but the dataset's items have no R / T / has_pose")
    if not bool(has_pose.all()):
        missing = [int(i) for i, ok in zip(batch["index"], has_pose.tolist()) if not ok]
        raise ValueError(f"oracle_pose needs a ground-truth pose for every item; items {missing} have none")


@torch.no_grad()
def evaluate(
    model: EvaluableModel,
    dataset: Dataset,
    options: EvalOptions,
    dataset_name: str = "dataset",
    device: str | torch.device = "cpu",
    shape_baseline: torch.Tensor | None = None,
) -> EvaluationResult:
    """Run the evaluation protocol of ``options.protocol`` over ``dataset``.

    Per image, the index of the selected pose candidate (argmax of ``pred.poses.probs``, (K, B)) is recorded as
    ``candidate`` and summarised per group as ``cand-share-min`` / ``cand-share-max`` and
    :attr:`EvaluationResult.candidate_shares`, when the model has K > 1 candidates and ``oracle_pose`` is off.

    Args:
        model: the model (moved to ``device`` and put in eval mode): any
            :class:`~unicorn.evaluation.interface.EvaluableModel` (a :class:`~unicorn.model.Unicorn`, a baseline).
        dataset: test items (``image``, ``mask``/``has_mask``, ``R``/``T``, ``points``/``normals``, ``keypoints``...
            as :mod:`unicorn.data` yields them); a :class:`~torch.utils.data.Subset` to evaluate part of it.
        options: :class:`EvalOptions`.
        dataset_name: group name for datasets without categories, and the label of the progress bar.
        device: where the model and the metrics run.
        shape_baseline: (V, 3) one mesh on the model's template topology, e.g. the training set's mean shape
            (:func:`~unicorn.evaluation.baselines.fit_mean_shape`), scored on every object beside the model
            (``chamfer-L1-ICP-mean-shape`` and ``shape-win``; needs ground-truth points and ICP).

    Returns:
        :class:`EvaluationResult`.

    Raises:
        ValueError: an empty dataset, or ``oracle_pose`` with an item without a ground-truth pose.
    """
    start = time.perf_counter()
    device = torch.device(device)
    model = model.to(device).eval()
    protocol = get_protocol(options.protocol)
    size = model.config["image_size"]
    faces = model.template.faces
    if shape_baseline is not None:
        V = model.template.num_verts
        if not isinstance(shape_baseline, torch.Tensor) or shape_baseline.shape != (V, 3):
            shape = tuple(shape_baseline.shape) if isinstance(shape_baseline, torch.Tensor) else type(shape_baseline)
            raise ValueError(f"shape_baseline must be a ({V}, 3) mesh on the model's template topology, got {shape}")
        shape_baseline = shape_baseline.to(device=device, dtype=model.template.verts.dtype)
    group_of = group_namer(dataset, dataset_name)
    loader = DataLoader(
        dataset, batch_size=options.batch_size, shuffle=False, num_workers=options.num_workers, collate_fn=collate
    )
    acc = Accumulator()
    oracle = options.oracle_pose
    # with the oracle pose every image is rendered at its ground-truth pose: no candidate is selected
    record_candidates = model.n_candidates > 1 and not oracle
    if record_candidates:
        acc.n_candidates = model.n_candidates
    own_means = None
    if options.own_mean_shape and protocol.meshes is not None and options.icp_iterations > 0:
        own_means = _own_mean_shapes(model, loader, group_of, size, options, device)
    samples: list[Sample] = []
    bar = tqdm(
        total=len(dataset),
        desc=options.progress_label or f"eval {dataset_name}",
        unit="img",
        disable=not options.progress,
        leave=options.progress_leave,
    )
    for batch in loader:
        images = _resize_images(batch["image"].to(device), size)
        B = images.shape[0]
        if oracle:
            _require_poses(batch)
        pred = model.predict(images, average_texture=options.average_texture)
        # the pose everything is rendered and aligned with: the prediction's, or the ground truth's (oracle)
        if oracle:
            R, T = batch["R"].to(device=device, dtype=pred.R.dtype), batch["T"].to(device=device, dtype=pred.T.dtype)
        else:
            R, T = pred.R, pred.T
        rec, _ = model.render(pred.verts, pred.texture, R, T, pred.background)
        scores: dict[str, torch.Tensor] = {"rec-mse": (rec - images).square().flatten(1).mean(1)}

        has_mask = "mask" in batch and isinstance(batch.get("has_mask"), torch.Tensor) and bool(batch["has_mask"].all())
        mask_size = batch["mask"].shape[-1] if has_mask else size
        hard = hard_render(model, pred.verts, pred.texture, R, T, mask_size, options.mask_supersample)
        alpha = hard.images[:, 3:]  # each pixel's coverage; mask_iou's silhouette: more than half covered
        colors = None
        if has_mask and protocol.masks:
            gt_mask = batch["mask"].to(device)
            scores["mask-iou"] = mask_iou(alpha, gt_mask, reduction="none")
            # mean foreground colours: the input's inside its mask, the reconstruction's inside its silhouette,
            # both without the one-input-pixel border where colours mix with the background (COLOR_INTERIOR)
            small_mask = F.interpolate(gt_mask.float().reshape(B, 1, *gt_mask.shape[-2:]), size=(size, size))
            r_hard = COLOR_INTERIOR * max(1, round(mask_size / size))
            colors = (
                mean_foreground_color(hard.images[:, :3], alpha, interior=r_hard),
                mean_foreground_color(images, small_mask, interior=COLOR_INTERIOR),
            )

        groups = [group_of(batch, i) for i in range(B)]
        if protocol.meshes is not None and "points" in batch:
            with_pose = protocol.meshes == "posed"
            gt_index = _gt_indices(batch, device, pred.verts.dtype, options)
            # without a ground-truth pose only the ICP-registered numbers are meaningful: the rest is not computed
            mesh = _mesh_scores(model, pred.verts, batch, device, options, with_pose, R, T, gt_index, with_pose)
            if not with_pose:
                # no ground-truth pose: only the ICP-registered numbers are meaningful
                mesh = {k: v for k, v in mesh.items() if k.endswith("-ICP")}
            scores.update(mesh)
            if shape_baseline is not None and "chamfer-L1-ICP" in mesh:
                base_verts = shape_baseline.unsqueeze(0).expand(B, -1, -1)
                base = _mesh_scores(model, base_verts, batch, device, options, False, R, T, gt_index, False)
                base = base["chamfer-L1-ICP"]
                ours = mesh["chamfer-L1-ICP"]
                scores["chamfer-L1-ICP-mean-shape"] = base
                scores["shape-win"] = _wins(ours, base)
            if own_means is not None and "chamfer-L1-ICP" in mesh:
                # the same pose and alignment as the model's prediction: only the shape differs
                own_verts = torch.stack([own_means[g] for g in groups])
                own = _mesh_scores(model, own_verts, batch, device, options, with_pose, R, T, gt_index, False)
                own = own["chamfer-L1-ICP"]
                scores["chamfer-L1-ICP-own-mean"] = own
                scores["shape-win-own"] = _wins(mesh["chamfer-L1-ICP"], own)
        if _retrieves_shapes(protocol, options, batch):
            for i, g in enumerate(groups):
                obj = int(batch["model"][i])
                objects = acc.objects.setdefault(g, {})
                if obj not in objects:
                    objects[obj] = object_samples(batch["points"][i], options.shape_points, options.seed + obj)
                acc.shapes.setdefault(g, []).append(
                    ShapeEntry(
                        len(acc.rows) + i,  # the index its row will have
                        obj,
                        pred.verts[i].cpu(),
                        pred.canonical_verts[i].cpu(),
                        pred.scale[i].cpu(),
                        R[i].cpu(),
                        T[i].cpu(),
                        batch["R"][i].cpu(),
                    )
                )
        if protocol.poses and not oracle and bool(batch["has_pose"].all()):
            for i, g in enumerate(groups):
                # the index its row will have: the rows of this batch are appended below
                acc.poses.setdefault(g, []).append((len(acc.rows) + i, pred.R[i].cpu(), batch["R"][i].cpu()))
        chosen = pred.poses.probs.argmax(0).tolist() if record_candidates else None  # (B,) selected candidates
        if chosen is not None:
            for i, g in enumerate(groups):
                acc.candidates.setdefault(g, []).append(int(chosen[i]))
        if protocol.keypoints and isinstance(batch.get("keypoints"), torch.Tensor):
            seen = hard
            if options.visibility_supersample != options.mask_supersample:
                seen = hard_render(model, pred.verts, pred.texture, R, T, mask_size, options.visibility_supersample)
            visible = vertex_visibility(seen.face_ids, faces, pred.verts.shape[1])
            for i, g in enumerate(groups):
                acc.keypoint_frames[g] = int(mask_size)
                acc.keypoints.setdefault(g, []).append(
                    (pred.verts[i].cpu(), pred.R[i].cpu(), pred.T[i].cpu(), visible[i].cpu(), batch["keypoints"][i])
                )

        for i in range(B):
            row: dict[str, Any] = {"index": int(batch["index"][i]), "group": groups[i]}
            if chosen is not None:
                row["candidate"] = int(chosen[i])
            row.update({k: float(v[i]) for k, v in scores.items()})
            if colors is not None:
                acc.colors.setdefault(groups[i], []).append((len(acc.rows), colors[0][i].cpu(), colors[1][i].cpu()))
            acc.rows.append(row)
            if len(samples) < options.report_samples:
                samples.append(
                    Sample(
                        index=row["index"],
                        group=groups[i],
                        image=images[i].cpu(),
                        reconstruction=rec[i].cpu(),
                        alpha=alpha[i].cpu(),
                        mask=batch["mask"][i].cpu() if has_mask else None,
                        verts=pred.verts[i].cpu(),
                        texture=pred.texture[i].cpu(),
                        R=R[i].cpu(),
                        T=T[i].cpu(),
                        scores={k: v for k, v in row.items() if k not in ("index", "group")},
                    )
                )
        bar.update(B)
    bar.close()
    if not acc.rows:
        raise ValueError("the dataset is empty: nothing to evaluate")
    color_scores(acc)
    shape_scores(acc, faces, options)
    shares = {g: candidate_shares(c, acc.n_candidates) for g, c in acc.candidates.items()}
    table, columns = summary_table(acc, model, options, shares)
    return EvaluationResult(protocol.name, acc.rows, table, columns, samples, time.perf_counter() - start, shares)


def _retrieves_shapes(protocol: Protocol, options: EvalOptions, batch: Mapping[str, Any]) -> bool:
    """Whether the batch enters the shape retrieval: ground-truth points and poses, and each item's object."""
    return (
        options.shape_points > 0
        and protocol.meshes == "posed"
        and isinstance(batch.get("model"), torch.Tensor)
        and "points" in batch
        and isinstance(batch.get("has_pose"), torch.Tensor)
        and bool(batch["has_pose"].all())
    )


def _wins(ours: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
    """(B,) 1 where ``ours`` is the lower error, 0.5 on a tie, else 0."""
    return (ours < base).to(ours.dtype) + 0.5 * (ours == base).to(ours.dtype)


def _own_mean_shapes(
    model: EvaluableModel,
    loader: DataLoader,
    group_of: Callable[[Mapping[str, Any], int], str],
    size: int,
    options: EvalOptions,
    device: torch.device,
) -> dict[str, torch.Tensor]:
    """Per group, the model's average predicted mesh (V, 3) over the evaluated images (a forward pass only)."""
    sums: dict[str, torch.Tensor] = {}
    counts: dict[str, int] = {}
    for batch in loader:
        verts = model.predict(
            _resize_images(batch["image"].to(device), size), average_texture=options.average_texture
        ).verts
        for i in range(verts.shape[0]):
            g = group_of(batch, i)
            sums[g] = sums[g] + verts[i] if g in sums else verts[i].clone()
            counts[g] = counts.get(g, 0) + 1
    return {g: sums[g] / counts[g] for g in sums}
