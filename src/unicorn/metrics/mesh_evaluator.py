"""The ShapeNet mesh metrics of UNICORN's evaluation for a batch of predicted meshes.

Per object (``final_scores.tsv`` columns):

- ``chamfer-L1`` and ``normal-cos``: the prediction, mapped into the ground-truth object frame with the
  predicted and ground-truth poses when they are given
  (:func:`~unicorn.metrics.alignment.align_with_gt_pose`), is sampled with ``num_points`` area-uniform points
  and normals and compared with the ground-truth cloud;
- ``chamfer-L1-ICP`` and ``normal-cos-ICP``: the (aligned) prediction is normalised to the unit cube
  (:func:`~unicorn.metrics.alignment.normalize_to_unit_cube`), resampled, registered onto the ground truth by
  :func:`~unicorn.metrics.icp.gradient_icp` (rotation, translation, anisotropic scale; Adam 0.01;
  ``icp_iterations``) and compared again, its normals transformed with the points;
- ``iou-3d`` and ``iou-3d-ICP``: 3D IoU of the same predicted samples (GT-pose aligned, and after ICP) and the
  ground-truth cloud, both voxelised solid at 32^3 over the unit cube (surface cells, one-cell closing, holes
  filled: :func:`~unicorn.metrics.voxels.point_cloud_voxel_iou`).

UNICORN's final evaluation uses 100k points and 100 ICP iterations, its validation 50k points and 30
iterations. Average the per-object values over the test objects of a class, then over classes.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from unicorn.checks import ShapeError, check_mesh, check_normals, check_points, check_same_batch

from .alignment import align_with_gt_pose, normalize_to_unit_cube
from .chamfer import CHAMFER_FACTOR, point_cloud_scores
from .icp import gradient_icp
from .nn import Backend, NearestNeighborIndex
from .sampling import sample_points_from_meshes
from .voxels import point_cloud_voxel_iou

__all__ = ["GT_EXTENT", "GT_EXTENT_TOLERANCE", "SHAPENET_METRICS", "evaluate_meshes"]

SHAPENET_METRICS = ("chamfer-L1", "chamfer-L1-ICP", "normal-cos", "normal-cos-ICP", "iou-3d", "iou-3d-ICP")

#: a ground-truth cloud's largest ``|coord|``, and how far from it one may be: the clouds fill the unit cube
GT_EXTENT, GT_EXTENT_TOLERANCE = 0.5, 0.01


def evaluate_meshes(
    verts: torch.Tensor,
    faces: torch.Tensor,
    gt_points: torch.Tensor,
    gt_normals: torch.Tensor | None = None,
    *,
    R_pred: torch.Tensor | None = None,
    T_pred: torch.Tensor | None = None,
    R_gt: torch.Tensor | None = None,
    T_gt: torch.Tensor | None = None,
    num_points: int = 100000,
    run_direct: bool = True,
    run_icp: bool = True,
    icp_iterations: int = 100,
    icp_lr: float = 0.01,
    seed: int = 0,
    check_gt_range: bool = True,
    backend: Backend = "auto",
    workers: int = 1,
    voxel_resolution: int = 32,
    gt_index: NearestNeighborIndex | None = None,
) -> dict[str, torch.Tensor]:
    """Chamfer-L1, normal consistency and 3D IoU, with GT-pose alignment and after unit-cube normalisation plus ICP.

    Args:
        verts: (B, V, 3) predicted vertices in the predicted object frame.
        faces: (F, 3) long faces shared by the batch.
        gt_points: (B, M, 3) ground-truth surface points in the ground-truth object frame, in [-0.5, 0.5]^3.
        gt_normals: (B, M, 3) their normals; without them the ``normal-cos`` entries are left out.
        R_pred: (B, 3, 3) predicted world-to-view rotations; give all four poses or none (no alignment, e.g.
            Pascal3D+, where only the ICP numbers are meaningful unless the canonical axes match).
        T_pred: (B, 3) predicted translations.
        R_gt: (B, 3, 3) ground-truth rotations, same convention.
        T_gt: (B, 3) ground-truth translations.
        num_points: points sampled on each predicted mesh (100k final, 50k validation).
        run_direct: compute the metrics without ICP (``chamfer-L1``, ``normal-cos``, ``iou-3d``).
        run_icp: also compute the ``-ICP`` metrics.
        icp_iterations: Adam iterations of the ICP (100 final, 30 validation).
        icp_lr: Adam learning rate of the ICP.
        seed: seed of the point sampling (the ICP branch uses ``seed + 1``).
        check_gt_range: raise unless every ground-truth cloud has ``max |coord|`` within 0.01 of 0.5.
        backend: nearest-neighbour backend, see :func:`unicorn.metrics.nn.nearest_neighbors`.
        workers: kdtree query threads.
        voxel_resolution: cells per axis of the unit cube for the 3D IoU.
        gt_index: a :class:`~unicorn.metrics.nn.NearestNeighborIndex` over ``gt_points`` (the same points and
            dtype as ``verts``) to reuse, e.g. when several predictions are scored against one ground truth;
            ``backend`` and ``workers`` are then its own. None: one is built here.

    Returns:
        dict of (B,) tensors keyed by :data:`SHAPENET_METRICS` (``chamfer-L1`` already multiplied by 10).

    Raises:
        ValueError: on malformed inputs, partial poses, a ground truth outside the unit cube, or a ``gt_index``
            of another shape than ``gt_points``.
    """
    poses = (R_pred, T_pred, R_gt, T_gt)
    _check_inputs(verts, faces, gt_points, gt_normals, poses, check_gt_range, gt_index)
    with torch.no_grad():
        gt_points = gt_points.to(verts.dtype)
        if gt_index is None:
            # one search structure over the ground truth for the direct scores, the ICP and the scores after it
            gt_index = NearestNeighborIndex(gt_points, backend=backend, workers=workers)
        gt = _GroundTruth(gt_points, None if gt_normals is None else gt_normals.to(verts.dtype), gt_index)
        if R_pred is not None:
            verts = align_with_gt_pose(verts, R_pred, T_pred, R_gt, T_gt)  # type: ignore[arg-type]
        results: dict[str, torch.Tensor] = {}
        if run_direct:
            points, normals = sample_points_from_meshes(verts, faces, num_points, seed=seed)
            results.update(_scores(points, normals, gt, voxel_resolution, suffix=""))
        if run_icp:
            points, normals = sample_points_from_meshes(
                normalize_to_unit_cube(verts)[0], faces, num_points, seed=seed + 1
            )
            results.update(_scores_after_icp(points, normals, gt, icp_iterations, icp_lr, voxel_resolution))
    return {k: results[k] for k in SHAPENET_METRICS if k in results}


def _scores_after_icp(
    points: torch.Tensor, normals: torch.Tensor, gt: _GroundTruth, n_iter: int, lr: float, voxel_resolution: int
) -> dict[str, torch.Tensor]:
    """The ``-ICP`` scores: the unit-cube-normalised samples (B, N, 3) aligned to the ground truth by the
    anisotropic-scale gradient ICP, then scored."""
    icp = gradient_icp(
        points,
        gt.points,
        normals,
        n_iter=n_iter,
        lr=lr,
        estimate_scale=True,
        anisotropic_scale=True,
        tgt_index=gt.index,
    )
    assert icp.normals is not None
    return _scores(icp.points, icp.normals, gt, voxel_resolution, suffix="-ICP")


class _GroundTruth(NamedTuple):
    """The ground truth of a batch: points (B, M, 3), normals (B, M, 3) or None, and the search index over them."""

    points: torch.Tensor
    normals: torch.Tensor | None
    index: NearestNeighborIndex


def _check_inputs(
    verts: torch.Tensor,
    faces: torch.Tensor,
    gt_points: torch.Tensor,
    gt_normals: torch.Tensor | None,
    poses: tuple[torch.Tensor | None, ...],
    check_gt_range: bool,
    gt_index: NearestNeighborIndex | None,
) -> None:
    check_mesh(verts, faces)
    check_points(gt_points, "gt_points")
    check_same_batch(verts, gt_points, "verts", "gt_points")
    check_normals(gt_normals, gt_points, "gt_normals")
    if any(p is not None for p in poses) and any(p is None for p in poses):
        raise ValueError("give all of R_pred, T_pred, R_gt, T_gt or none of them")
    if check_gt_range:
        extent = gt_points.detach().abs().amax(dim=(1, 2))
        if ((extent - GT_EXTENT).abs() > GT_EXTENT_TOLERANCE).any():
            raise ValueError(
                f"ground-truth clouds must have max |coord| = {GT_EXTENT} +- {GT_EXTENT_TOLERANCE} (unit cube), got "
                f"{extent.tolist()}"
            )
    if gt_index is not None and gt_index.y.shape != gt_points.shape:
        raise ShapeError(f"gt_index must index gt_points {tuple(gt_points.shape)}, got {tuple(gt_index.y.shape)}")


def _scores(
    points: torch.Tensor, normals: torch.Tensor, gt: _GroundTruth, voxel_resolution: int, suffix: str
) -> dict[str, torch.Tensor]:
    """``chamfer-L1``, ``normal-cos`` (with ground-truth normals) and ``iou-3d`` of predicted samples (B, N, 3)
    with their normals, the keys ending in ``suffix``."""
    s = point_cloud_scores(
        points,
        gt.points,
        None if gt.normals is None else normals,
        gt.normals,
        factor=CHAMFER_FACTOR,
        gt_index=gt.index,
    )
    out = {"chamfer-L1" + suffix: s.chamfer_l1}
    if s.normal_cos is not None:
        out["normal-cos" + suffix] = s.normal_cos
    out["iou-3d" + suffix] = point_cloud_voxel_iou(points, gt.points, voxel_resolution)
    return out
