"""The mean shape of a set of shapes: the single mesh on a template's topology closest on average to all of them
(:func:`fit_mean_shape`), the reference shape of :func:`~unicorn.evaluation.baselines.mean_shape_baseline` and,
one per category (:func:`fit_mean_shapes`), of the evaluation's ``chamfer-L1-ICP-mean-shape``."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tqdm.auto import tqdm

from unicorn.checks import ShapeError, check_faces, check_shape
from unicorn.metrics import NearestNeighborIndex, gather_points, sample_points_from_meshes
from unicorn.objectives.losses import NormalConsistencyLoss, UniformLaplacianLoss

__all__ = ["fit_mean_shape", "fit_mean_shapes"]


def _stack_clouds(
    point_clouds: Sequence[torch.Tensor] | torch.Tensor,
    num_points: int,
    generator: torch.Generator,
    device: torch.device,
    dtype: torch.dtype,
) -> torch.Tensor:
    """(M, num_points, 3): each cloud subsampled without replacement, or (if smaller) padded by resampling."""
    if isinstance(point_clouds, torch.Tensor):
        check_shape(point_clouds, "M, N, 3", "point_clouds")
    clouds = list(point_clouds)
    if not clouds:
        raise ValueError("point_clouds is empty: there is no shape to fit")
    out = []
    for i, cloud in enumerate(clouds):
        cloud = torch.as_tensor(cloud)
        check_shape(cloud, "N, 3", f"point cloud {i}")
        if cloud.shape[0] == 0:
            raise ShapeError(f"point cloud {i} must have shape (N, 3) with N >= 1, got {tuple(cloud.shape)}")
        if not bool(torch.isfinite(cloud).all()):
            raise ValueError(f"point cloud {i} has non-finite coordinates")
        n = cloud.shape[0]
        if n >= num_points:
            keep = torch.randperm(n, generator=generator)[:num_points]
        else:
            # every point once, then uniform draws: the mean distance to the cloud stays unbiased
            keep = torch.cat([torch.arange(n), torch.randint(n, (num_points - n,), generator=generator)])
        out.append(cloud[keep].to(device=device, dtype=dtype))
    return torch.stack(out)


def fit_mean_shape(
    template_verts: torch.Tensor,
    faces: torch.Tensor,
    point_clouds: Sequence[torch.Tensor] | torch.Tensor,
    iterations: int = 300,
    lr: float = 0.01,
    num_points: int = 2000,
    smooth_weight: float = 0.1,
    normal_weight: float = 0.01,
    shapes_per_step: int = 16,
    seed: int = 0,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
) -> torch.Tensor | None:
    """The single mesh (template topology) closest on average to a set of shapes, in their object frame.

    Per-vertex offsets of the template are optimised with Adam (learning rate cosine-annealed to a tenth) to
    minimise ``mean_shapes chamfer_L1(mesh, shape) + smooth_weight * laplacian + normal_weight * normal``, where
    ``chamfer_L1`` is the symmetric mean nearest-neighbour distance ``(accuracy + completeness) / 2`` (no x10
    factor) between ``num_points`` area-uniform samples of the mesh (redrawn every iteration, differentiable
    w.r.t. the vertices) and the shape's points, and the regularisers are the training losses
    :class:`~unicorn.objectives.losses.UniformLaplacianLoss` and
    :class:`~unicorn.objectives.losses.NormalConsistencyLoss`, which keep the mesh smooth and unfolded. Each
    iteration uses a random mini-batch of ``shapes_per_step`` shapes (all of them when there are fewer).

    Args:
        template_verts: (V, 3) initial vertices (e.g. ``model.template.verts``); the fit runs on their device.
        faces: (F, 3) integer faces of a closed manifold mesh (the normal regulariser needs one).
        point_clouds: the M shapes, in the frame the mesh is wanted in: a sequence of (N_i, 3) tensors or one
            (M, N, 3) tensor. Each is subsampled to ``num_points`` once (padded by resampling if smaller).
        iterations: Adam steps (0 returns the template).
        lr: initial Adam learning rate, in object units per step.
        num_points: points sampled on the mesh per iteration and kept per shape.
        smooth_weight: weight of the uniform Laplacian regulariser.
        normal_weight: weight of the normal-consistency regulariser.
        shapes_per_step: shapes per iteration.
        seed: seed of the subsampling, the mini-batches and the surface samples.
        progress: show a progress bar.
        should_stop: asked before each iteration; True ends the fit there (a run stopped by a signal).

    Returns:
        (V, 3) fitted vertices (detached), on the template's device and dtype; None when ``should_stop`` ended
        the fit.

    Raises:
        ValueError: malformed template, faces or clouds, no clouds, or invalid settings.
    """
    check_shape(template_verts, "V, 3", "template_verts")
    if not template_verts.dtype.is_floating_point or not bool(torch.isfinite(template_verts).all()):
        raise ValueError("template_verts must be finite floating-point coordinates")
    check_faces(faces, template_verts.shape[0])
    if iterations < 0 or num_points < 1 or shapes_per_step < 1:
        raise ValueError(
            f"need iterations >= 0, num_points >= 1 and shapes_per_step >= 1, got {iterations}, {num_points}, "
            f"{shapes_per_step}"
        )
    if not lr > 0 or smooth_weight < 0 or normal_weight < 0:
        raise ValueError(f"need lr > 0 and non-negative weights, got {lr}, {smooth_weight}, {normal_weight}")
    generator = torch.Generator().manual_seed(int(seed))  # CPU draws: the same fit on every device
    clouds = _stack_clouds(point_clouds, num_points, generator, template_verts.device, template_verts.dtype)
    if iterations == 0:
        return template_verts.detach().clone()
    with torch.enable_grad():  # callers may be under no_grad (e.g. inside an evaluation)
        return _fit_offsets(
            template_verts.detach(), faces, clouds, generator, iterations, lr, num_points, smooth_weight,
            normal_weight, shapes_per_step, progress, should_stop,
        )  # fmt: skip


def fit_mean_shapes(
    template_verts: torch.Tensor,
    faces: torch.Tensor,
    point_clouds: Mapping[str, Sequence[torch.Tensor] | torch.Tensor],
    should_stop: Callable[[], bool] | None = None,
    **fit_kwargs: Any,
) -> dict[str, torch.Tensor] | None:
    """The mean shape of each group of shapes (e.g. each category's training shapes): :func:`fit_mean_shape` of
    every group's clouds on its own, with the same settings and seed (the mesh that fitting that group alone gives).

    Args:
        template_verts: (V, 3) initial vertices; faces: (F, 3), as :func:`fit_mean_shape`.
        point_clouds: group name -> the group's shapes, as :func:`fit_mean_shape` takes them.
        should_stop: asked before each iteration of every fit; True ends them all.
        **fit_kwargs: the other options of :func:`fit_mean_shape`.

    Returns:
        group name -> (V, 3) fitted vertices, in ``point_clouds``' order; None when ``should_stop`` ended a fit.
    """
    fitted: dict[str, torch.Tensor] = {}
    for group, clouds in point_clouds.items():
        verts = fit_mean_shape(template_verts, faces, clouds, should_stop=should_stop, **fit_kwargs)
        if verts is None:
            return None
        fitted[group] = verts
    return fitted


def _fit_offsets(
    base: torch.Tensor,
    faces: torch.Tensor,
    clouds: torch.Tensor,
    generator: torch.Generator,
    iterations: int,
    lr: float,
    num_points: int,
    smooth_weight: float,
    normal_weight: float,
    shapes_per_step: int,
    progress: bool,
    should_stop: Callable[[], bool] | None = None,
) -> torch.Tensor | None:
    """:func:`fit_mean_shape`'s optimisation: ``base`` (V, 3) plus Adam-fitted offsets, to the clouds (M, N, 3);
    None when ``should_stop`` ends it."""
    device, M = base.device, clouds.shape[0]
    faces = faces.long().to(device)
    targets = NearestNeighborIndex(clouds)  # the shapes' search structures, built once for every iteration
    laplacian = UniformLaplacianLoss(faces, base.shape[0]).to(device)
    normal = NormalConsistencyLoss(faces).to(device)
    offsets = torch.zeros_like(base, requires_grad=True)
    optimizer = torch.optim.Adam([offsets], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, iterations, eta_min=0.1 * lr)
    b = min(shapes_per_step, M)
    bar = tqdm(range(iterations), desc="mean shape", unit="it", disable=not progress)
    for _ in bar:
        if should_stop is not None and should_stop():
            return None
        pick = torch.randperm(M, generator=generator)[:b].to(device) if b < M else None
        target = clouds if pick is None else clouds[pick]  # (b, N, 3)
        verts = (base + offsets).unsqueeze(0)  # (1, V, 3)
        points, _ = sample_points_from_meshes(verts, faces, num_points, generator=generator)
        chamfer = _sample_chamfer(points, target, targets if pick is None else targets.select(pick))
        loss = chamfer + smooth_weight * laplacian(verts) + normal_weight * normal(verts)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        if progress:
            bar.set_postfix(chamfer=f"{float(chamfer):.4f}")
    return (base + offsets).detach()


def _sample_chamfer(points: torch.Tensor, target: torch.Tensor, index: NearestNeighborIndex) -> torch.Tensor:
    """``chamfer_l1(points.expand(b, -1, -1), target, factor=1.0).mean()``, the same operations (the fit's samples
    depend on every rounding of it), for one sample (1, N, 3) of a mesh against b shapes (b, N', 3) with their
    ``index``: the shapes' trees are reused, and their points are searched in one tree of the sample."""
    b = target.shape[0]
    expanded = points.expand(b, -1, -1)
    d_pred, _ = index.query(expanded)
    idx_gt = NearestNeighborIndex(points.detach()).indices(target.reshape(1, -1, 3)).view(b, -1)
    d_gt = torch.linalg.vector_norm(target - gather_points(expanded, idx_gt), dim=-1)
    factor = 1.0
    return (factor * 0.5 * (d_pred.mean(dim=1) + d_gt.mean(dim=1))).mean()
