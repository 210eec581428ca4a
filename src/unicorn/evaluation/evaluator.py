"""The evaluation loop: a model and a dataset in, per-image scores, a per-group table and report samples out.

What each protocol scores is :mod:`unicorn.evaluation.protocols` (its docstring describes every metric); how each
family of metrics is measured on a batch is :mod:`unicorn.evaluation.measurements`; this module builds the
evaluation items of a dataset and runs the loop.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset, Subset
from tqdm.auto import tqdm

from unicorn.data import build_dataset
from unicorn.data.common import OnError
from unicorn.data.images import DatasetError
from unicorn.data.registry import dataset_spec
from unicorn.errors import ignore_stop_signals
from unicorn.evaluation.interface import EvaluableModel, spread_indices
from unicorn.evaluation.measurements import EvaluatedBatch, checked_shape_baseline, measurements_for
from unicorn.evaluation.protocols import EvalOptions, EvaluationResult, Sample, get_protocol
from unicorn.evaluation.rendering import hard_render
from unicorn.evaluation.tables import Accumulator, candidate_shares, color_scores, shape_scores, summary_table

__all__ = ["build_eval_dataset", "candidate_shares", "category_group", "collate", "evaluate", "group_namer"]

log = logging.getLogger(__name__)


def build_eval_dataset(
    name: str,
    root: str,
    split: str = "test",
    img_size: int = 64,
    categories: str | list[str] | None = None,
    max_images: int | None = None,
    seed: int = 0,
    on_error: OnError = "raise",
    options: Mapping[str, Any] | None = None,
) -> Dataset:
    """The evaluation items of a dataset, as its protocol needs them.

    ShapeNet / synthetic: one fixed random view per model (``seed``) with the ground-truth point clouds; CUB:
    masks and keypoints at 256 px (UNICORN's keypoint frame); Pascal3D+: with the CAD clouds (its validation
    split too, training images).
    With ``max_images``, that many items spread evenly over the split (so every category is represented).

    Args:
        name: a registered dataset name (:data:`unicorn.data.registry.DATASETS`).
        root: its root folder (for ``synthetic``, the generated dataset, which holds ``metadata.yaml``).
        split: ``"train"``, ``"val"`` or ``"test"``.
        img_size: the model's input side (ShapeNet images keep their size and are resized in :func:`evaluate`).
        categories: ShapeNet / synthetic categories (names or synsets), None for all.
        max_images: evaluate at most this many items.
        seed: the view choice of ShapeNet.
        on_error: ``"raise"``: an unreadable image is an error; ``"skip"``: it is skipped with a warning
            (:class:`~unicorn.data.common.SkippedFileWarning`) and :func:`evaluate` scores each readable item once.
        options: a training run's dataset options: those that say which data it read
            (:attr:`~unicorn.data.registry.DatasetSpec.data_options`: LSUN's ``tag``...) are kept, the others
            (how training draws from the data) left out.
    """
    spec = dataset_spec(name)
    kept = {key: value for key, value in (options or {}).items() if key in spec.data_options}
    options = {**kept, **spec.eval_options}
    dataset = build_dataset(
        name, split, root, img_size=img_size, categories=categories, seed=seed, on_error=on_error, **options
    )
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


def _first_reads(batch: dict[str, Any], seen: set[int]) -> dict[str, Any] | None:
    """``batch`` without the items whose ``index`` is in ``seen`` or repeats an earlier one of the batch (a dataset
    skipping an unreadable file returns the next readable item in its place, already scored or still to be); None
    when none is left. The indices kept are added to ``seen``."""
    if "index" not in batch:  # a dataset of another library: its items are taken as they come
        return batch
    indices = [int(i) for i in batch["index"]]
    keep = []
    for position, index in enumerate(indices):
        if index not in seen:
            seen.add(index)
            keep.append(position)
    if len(keep) == len(indices):
        return batch
    if not keep:
        return None
    rows = torch.tensor(keep)
    return {
        key: value[rows] if isinstance(value, torch.Tensor) else [value[k] for k in keep]
        for key, value in batch.items()
    }


def _base_dataset(dataset: Dataset) -> Dataset:
    while isinstance(dataset, Subset):
        dataset = dataset.dataset
    return dataset


def category_group(metadata: Mapping[str, Mapping[str, str]], synset: str) -> str:
    """The evaluation group of a ShapeNet-format category: the first name of its ``metadata.yaml`` entry, else its
    synset (categories of the same first name share a group)."""
    return metadata[synset]["name"].split(",")[0] or synset


def group_namer(dataset: Dataset, dataset_name: str) -> Callable[[Mapping[str, Any], int], str]:
    """A function ``(batch, i) -> group name``: the ShapeNet category's (:func:`category_group`), else the dataset
    name."""
    base = _base_dataset(dataset)
    synsets = getattr(base, "synsets", None)
    metadata = getattr(base, "metadata", None)
    if synsets is None or metadata is None:
        return lambda batch, i: dataset_name
    names = [category_group(metadata, s) for s in synsets]
    return lambda batch, i: names[int(batch["category"][i])]


def _resize_images(images: torch.Tensor, size: int) -> torch.Tensor:
    if images.shape[-1] == size and images.shape[-2] == size:
        return images
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False, antialias=True).clamp(0, 1)


def _indices(batch: Mapping[str, Any], first_row: int) -> list[int]:
    """Each item's ``index``; for items without one (a dataset of another library), its position in the evaluation,
    the batch's first item being at ``first_row``."""
    if "index" in batch:
        return [int(i) for i in batch["index"]]
    return list(range(first_row, first_row + len(batch["image"])))


def _require_poses(batch: Mapping[str, Any], first_row: int) -> None:
    """Raise unless every item of the batch has a ground-truth pose (what ``oracle_pose`` substitutes)."""
    has_pose = batch.get("has_pose")
    if not isinstance(has_pose, torch.Tensor) or "R" not in batch or "T" not in batch:
        raise ValueError("oracle_pose needs ground-truth poses, but the dataset's items have no R / T / has_pose")
    if not bool(has_pose.all()):
        missing = [i for i, ok in zip(_indices(batch, first_row), has_pose.tolist()) if not ok]
        raise ValueError(f"oracle_pose needs a ground-truth pose for every item; items {missing} have none")


@torch.no_grad()
def evaluate(
    model: EvaluableModel,
    dataset: Dataset,
    options: EvalOptions,
    dataset_name: str = "dataset",
    device: str | torch.device = "cpu",
    shape_baseline: torch.Tensor | Mapping[str, torch.Tensor] | None = None,
) -> EvaluationResult:
    """Run the evaluation protocol of ``options.protocol`` over ``dataset``.

    Each batch is predicted and rendered once, then measured by the protocol's measurements
    (:func:`~unicorn.evaluation.measurements.measurements_for`); the set-level metrics follow the loop.

    Per image, the index of the selected pose candidate (argmax of ``pred.poses.probs``, (K, B)) is recorded as
    ``candidate`` and summarised per group as ``cand-share-min`` / ``cand-share-max`` and
    :attr:`EvaluationResult.candidate_shares`, when the model has K > 1 candidates and ``oracle_pose`` is off.

    Args:
        model: the model (moved to ``device`` and put in eval mode): any
            :class:`~unicorn.evaluation.interface.EvaluableModel` (a :class:`~unicorn.model.Unicorn`, a baseline).
        dataset: test items (``image``, ``mask``/``has_mask``, ``R``/``T``, ``points``/``normals``, ``keypoints``...
            as :mod:`unicorn.data` yields them); a :class:`~torch.utils.data.Subset` to evaluate part of it. An item
            whose ``index`` was scored already (the next readable item that a dataset skipping an unreadable file
            returns in its place) is not scored again; items without ``index`` are numbered by their position.
        options: :class:`EvalOptions`.
        dataset_name: group name for datasets without categories, and the label of the progress bar.
        device: where the model and the metrics run.
        shape_baseline: a mesh on the model's template topology scored on every object beside the model
            (``chamfer-L1-ICP-mean-shape`` and ``shape-win``; needs ground-truth points and ICP), e.g. a mean
            training shape (:func:`~unicorn.evaluation.mean_shape.fit_mean_shape`): one (V, 3) mesh for every
            group, or a mapping group name -> (V, 3) mesh, each group's objects scored against its own (every
            evaluated group must have one; :func:`~unicorn.evaluation.mean_shape.fit_mean_shapes` fits one per
            category).

    Returns:
        :class:`EvaluationResult`.

    Raises:
        ValueError: an empty dataset, or ``oracle_pose`` with an item without a ground-truth pose.
        ShapeError: a ``shape_baseline`` mesh is not (V, 3) on the model's template.
        ValueError: ``shape_baseline`` is a mapping without a mesh for an evaluated group.
    """
    start = time.perf_counter()
    device = torch.device(device)
    model = model.to(device).eval()
    protocol = get_protocol(options.protocol)
    if shape_baseline is not None:
        shape_baseline = checked_shape_baseline(shape_baseline, model, device)
    group_of = group_namer(dataset, dataset_name)
    loader = DataLoader(
        dataset,
        batch_size=options.batch_size,
        shuffle=False,
        num_workers=options.num_workers,
        collate_fn=collate,
        worker_init_fn=ignore_stop_signals,  # a signal to the process group stops the command, not its workers
    )
    own_means = None
    if options.own_mean_shape and protocol.meshes is not None and options.icp_iterations <= 0:
        log.warning("note: the model's own average shape is not scored (own_mean_shape): it is scored after ICP, "
                    "and icp_iterations is 0")  # fmt: skip
    elif options.own_mean_shape and protocol.meshes is not None:
        own_means = _own_mean_shapes(model, loader, group_of, model.config["image_size"], options, device)
    measurements = measurements_for(protocol, options, model, shape_baseline, own_means)
    acc = Accumulator()
    samples: list[Sample] = []
    bar = tqdm(
        total=len(dataset),
        desc=options.progress_label or f"eval {dataset_name}",
        unit="img",
        disable=not options.progress,
        leave=options.progress_leave,
    )
    seen: set[int] = set()
    for loaded in loader:
        batch = _first_reads(loaded, seen)
        if batch is not None:
            view = _predict_and_render(model, batch, options, group_of, len(acc.rows), device)
            for measure in measurements:
                measure(view, acc)
            _append_rows(view, acc, samples, options.report_samples)
        bar.update(len(loaded["image"]))
    bar.close()
    if not acc.rows:
        raise DatasetError("the dataset is empty: nothing to evaluate")
    color_scores(acc)
    shape_scores(acc, model.template.faces, options)
    shares = {g: candidate_shares(c, acc.n_candidates) for g, c in acc.candidates.items()}
    table, columns = summary_table(acc, model, options, shares)
    # the scores computed over whole groups (colour, rotation after alignment, shape retrieval) went into the
    # rows after the samples were taken: sample k is row k
    for k, sample in enumerate(samples):
        sample.scores = {key: value for key, value in acc.rows[k].items() if key not in ("index", "group")}
    return EvaluationResult(protocol.name, acc.rows, table, columns, samples, time.perf_counter() - start, shares)


def _predict_and_render(
    model: EvaluableModel,
    batch: Mapping[str, Any],
    options: EvalOptions,
    group_of: Callable[[Mapping[str, Any], int], str],
    first_row: int,
    device: torch.device,
) -> EvaluatedBatch:
    """Predict a batch, render it soft (``rec-mse``) and hard (silhouettes at the ground-truth masks' side)."""
    size = model.config["image_size"]
    images = _resize_images(batch["image"].to(device), size)
    if options.oracle_pose:
        _require_poses(batch, first_row)
    pred = model.predict(images, average_texture=options.average_texture)
    # the pose everything is rendered and aligned with: the prediction's, or the ground truth's (oracle)
    if options.oracle_pose:
        R, T = batch["R"].to(device=device, dtype=pred.R.dtype), batch["T"].to(device=device, dtype=pred.T.dtype)
    else:
        R, T = pred.R, pred.T
    rec, _ = model.render(pred.verts, pred.texture, R, T, pred.background)
    has_mask = "mask" in batch and isinstance(batch.get("has_mask"), torch.Tensor) and bool(batch["has_mask"].all())
    mask_size = batch["mask"].shape[-1] if has_mask else size
    hard = hard_render(model, pred.verts, pred.texture, R, T, mask_size, options.mask_supersample)
    groups = [group_of(batch, i) for i in range(images.shape[0])]
    view = EvaluatedBatch(batch, images, pred, R, T, rec, hard, mask_size, has_mask, groups, first_row)
    view.scores["rec-mse"] = (rec - images).square().flatten(1).mean(1)
    return view


def _append_rows(view: EvaluatedBatch, acc: Accumulator, samples: list[Sample], report_samples: int) -> None:
    """The batch's per-image rows into ``acc.rows``, and its first images into ``samples`` up to ``report_samples``."""
    batch = view.batch
    indices = _indices(batch, view.first_row)
    for i, group in enumerate(view.groups):
        row: dict[str, Any] = {"index": indices[i], "group": group}
        row.update({k: v[i] for k, v in view.labels.items()})
        row.update({k: float(v[i]) for k, v in view.scores.items()})
        acc.rows.append(row)
        if len(samples) < report_samples:
            samples.append(
                Sample(
                    index=row["index"],
                    group=group,
                    image=view.images[i].cpu(),
                    reconstruction=view.rec[i].cpu(),
                    alpha=view.alpha[i].cpu(),
                    mask=batch["mask"][i].cpu() if view.has_mask else None,
                    verts=view.pred.verts[i].cpu(),
                    texture=view.pred.texture[i].cpu(),
                    R=view.R[i].cpu(),
                    T=view.T[i].cpu(),
                    scores={k: v for k, v in row.items() if k not in ("index", "group")},
                )
            )


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
    seen: set[int] = set()
    for loaded in loader:
        batch = _first_reads(loaded, seen)
        if batch is None:
            continue
        verts = model.predict(
            _resize_images(batch["image"].to(device), size), average_texture=options.average_texture
        ).verts
        for i in range(verts.shape[0]):
            g = group_of(batch, i)
            sums[g] = sums[g] + verts[i] if g in sums else verts[i].clone()
            counts[g] = counts.get(g, 0) + 1
    return {g: sums[g] / counts[g] for g in sums}
