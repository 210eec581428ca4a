"""Chamfer-L1 and normal consistency as UNICORN (after DVR / Occupancy Networks) reports them.

For a prediction ``P`` and a ground truth ``G`` (point clouds with normals):

- accuracy = mean over ``p`` in ``P`` of the Euclidean distance to its nearest neighbour in ``G``;
- completeness = mean over ``g`` in ``G`` of the Euclidean distance to its nearest neighbour in ``P``;
- ``chamfer-L1 = CHAMFER_FACTOR * (accuracy + completeness) / 2`` with ``CHAMFER_FACTOR = 10`` (distances in
  units of a tenth of the unit cube's edge); "L1" means unsquared distances;
- ``normal-cos`` = mean of ``|cos|`` between each point's normal and its nearest neighbour's normal, averaged
  over both directions (the reference's ``1 - 0.5 * sum(mean(1 - |cos|))``).

All values are per batch element; average them over objects (then over classes) as the reference does.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from unicorn.checks import ShapeError, check_normals, check_points, check_same_batch

from .nn import Backend, NearestNeighborIndex, gather_points, nearest_neighbors, spatial_order

__all__ = [
    "CHAMFER_FACTOR",
    "PointCloudScores",
    "chamfer_l1",
    "chamfer_l2",
    "chamfer_matrix",
    "normal_consistency",
    "point_cloud_scores",
]

CHAMFER_FACTOR = 10.0


class PointCloudScores(NamedTuple):
    """Per-object scores between a predicted and a ground-truth point cloud.

    Attributes:
        chamfer_l1: (B,) ``factor * (accuracy + completeness) / 2``.
        accuracy: (B,) mean NN distance from the prediction to the ground truth (no factor).
        completeness: (B,) mean NN distance from the ground truth to the prediction (no factor).
        normal_cos: (B,) mean absolute cosine between matched normals, None without normals.
    """

    chamfer_l1: torch.Tensor
    accuracy: torch.Tensor
    completeness: torch.Tensor
    normal_cos: torch.Tensor | None


def _abs_cos(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.cosine_similarity(a, b, dim=-1, eps=1e-12).abs()


def point_cloud_scores(
    pred: torch.Tensor,
    gt: torch.Tensor,
    pred_normals: torch.Tensor | None = None,
    gt_normals: torch.Tensor | None = None,
    *,
    factor: float = CHAMFER_FACTOR,
    backend: Backend = "auto",
    workers: int = 1,
    gt_index: NearestNeighborIndex | None = None,
) -> PointCloudScores:
    """Chamfer-L1 (and normal consistency when normals are given) from one NN search per direction.

    Args:
        pred: (B, N, 3) predicted points.
        gt: (B, M, 3) ground-truth points.
        pred_normals: (B, N, 3) normals of ``pred`` (any length, they are normalised), optional.
        gt_normals: (B, M, 3) normals of ``gt``; give both normals or neither.
        factor: multiplier of the Chamfer distance, 10 as reported by UNICORN, DVR and ONet.
        backend: nearest-neighbour backend, see :func:`unicorn.metrics.nn.nearest_neighbors`.
        workers: kdtree query threads.
        gt_index: a :class:`~unicorn.metrics.nn.NearestNeighborIndex` over ``gt`` (the same points) to reuse;
            ``backend`` and ``workers`` are then its own. None: the clouds are searched here.

    Returns:
        :class:`PointCloudScores` of (B,) tensors.

    Raises:
        ValueError: on malformed shapes, empty clouds, only one set of normals, or a ``gt_index`` of another
            shape than ``gt``.
    """
    check_points(pred, "pred")
    check_points(gt, "gt")
    check_same_batch(pred, gt, "pred", "gt")
    if (pred_normals is None) != (gt_normals is None):
        raise ValueError("give normals for both clouds or for neither")
    check_normals(pred_normals, pred, "pred_normals")
    check_normals(gt_normals, gt, "gt_normals")
    if gt_index is None:
        d_pred, idx_pred = nearest_neighbors(pred, gt, backend=backend, workers=workers)
        d_gt, idx_gt = nearest_neighbors(gt, pred, backend=backend, workers=workers)
    else:
        if gt_index.y.shape != gt.shape:
            raise ShapeError(f"gt_index must index gt {tuple(gt.shape)}, got one over {tuple(gt_index.y.shape)}")
        order = spatial_order(pred)  # one visiting order of the prediction's points for both directions
        d_pred, idx_pred = gt_index.query(pred, order)
        d_gt, idx_gt = gt_index.reverse_query(pred, order)
    accuracy, completeness = d_pred.mean(dim=1), d_gt.mean(dim=1)
    normal_cos = None
    if pred_normals is not None and gt_normals is not None:
        cos_pred = _abs_cos(pred_normals, gather_points(gt_normals, idx_pred)).mean(dim=1)
        cos_gt = _abs_cos(gt_normals, gather_points(pred_normals, idx_gt)).mean(dim=1)
        normal_cos = 0.5 * (cos_pred + cos_gt)
    return PointCloudScores(factor * 0.5 * (accuracy + completeness), accuracy, completeness, normal_cos)


def chamfer_l1(
    pred: torch.Tensor,
    gt: torch.Tensor,
    *,
    factor: float = CHAMFER_FACTOR,
    backend: Backend = "auto",
    workers: int = 1,
) -> torch.Tensor:
    """Chamfer-L1 per object: ``factor * (accuracy + completeness) / 2`` with Euclidean NN distances.

    Args:
        pred: (B, N, 3) predicted points.
        gt: (B, M, 3) ground-truth points.
        factor: 10 as the reference reports it; 1 for the plain mean distance.
        backend: nearest-neighbour backend.
        workers: kdtree query threads.

    Returns:
        (B,) Chamfer-L1, differentiable w.r.t. both clouds.

    Example:
        >>> x = torch.zeros(1, 1, 3)
        >>> y = torch.tensor([[[0.0, 0.0, 0.1]]])
        >>> round(chamfer_l1(x, y).item(), 6)
        1.0
    """
    return point_cloud_scores(pred, gt, factor=factor, backend=backend, workers=workers).chamfer_l1


def normal_consistency(
    pred: torch.Tensor,
    pred_normals: torch.Tensor,
    gt: torch.Tensor,
    gt_normals: torch.Tensor,
    *,
    backend: Backend = "auto",
    workers: int = 1,
) -> torch.Tensor:
    """Normal consistency (``normal-cos``): mean ``|cos|`` between NN-matched normals, both directions
    averaged.

    Args:
        pred: (B, N, 3) predicted points.
        pred_normals: (B, N, 3) their normals.
        gt: (B, M, 3) ground-truth points.
        gt_normals: (B, M, 3) their normals.
        backend: nearest-neighbour backend.
        workers: kdtree query threads.

    Returns:
        (B,) values in [0, 1], 1 when matched normals are parallel or anti-parallel.
    """
    scores = point_cloud_scores(pred, gt, pred_normals, gt_normals, backend=backend, workers=workers)
    assert scores.normal_cos is not None
    return scores.normal_cos


def chamfer_l2(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    backend: Backend = "auto",
    workers: int = 1,
) -> torch.Tensor:
    """Squared Chamfer distance ``mean_x d^2(x, Y) + mean_y d^2(y, X)`` per batch element (the ICP objective).

    Args:
        x: (B, N, 3) points.
        y: (B, M, 3) points.
        backend: nearest-neighbour backend.
        workers: kdtree query threads.

    Returns:
        (B,) differentiable w.r.t. both clouds (the neighbour assignment is held fixed).
    """
    check_points(x, "x")
    check_points(y, "y")
    check_same_batch(x, y, "x", "y")
    d_x, _ = nearest_neighbors(x, y, backend=backend, workers=workers)
    d_y, _ = nearest_neighbors(y, x, backend=backend, workers=workers)
    return d_x.square().mean(dim=1) + d_y.square().mean(dim=1)


@torch.no_grad()
def chamfer_matrix(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    factor: float = CHAMFER_FACTOR,
    backend: Backend = "auto",
    workers: int = 1,
) -> torch.Tensor:
    """Chamfer-L1 between every cloud of ``x`` and every cloud of ``y`` (as :func:`chamfer_l1` scores one pair).

    One search structure per cloud (P + Q of them), each queried with the whole other set at once: 2 P Q
    nearest-neighbour queries, where scoring the P Q pairs with :func:`chamfer_l1` would also build 2 P Q trees.

    Args:
        x: (P, N, 3) points.
        y: (Q, M, 3) points, same dtype and device.
        factor: multiplier, as :func:`chamfer_l1`'s.
        backend: nearest-neighbour backend.
        workers: kdtree query threads.

    Returns:
        (P, Q) ``D[p, q] = chamfer_l1(x[p], y[q])``, without gradient.

    Example:
        >>> x = torch.zeros(2, 1, 3)
        >>> x[1, 0, 2] = 0.1
        >>> chamfer_matrix(x, x[:1]).flatten().tolist() == [0.0, chamfer_l1(x[1:], x[:1]).item()]
        True
    """
    check_points(x, "x")
    check_points(y, "y")
    P, Q = x.shape[0], y.shape[0]
    into_y = NearestNeighborIndex(y, backend=backend, workers=workers)
    into_x = NearestNeighborIndex(x, backend=backend, workers=workers)
    # each cloud visited in its own spatial order by all its queries
    x_orders, y_orders = spatial_order(x), spatial_order(y)
    accuracy = torch.stack(
        [into_y.query(xp.expand(Q, -1, -1), o.expand(Q, -1))[0].mean(dim=1) for xp, o in zip(x, x_orders)]
    )  # (P, Q)
    completeness = torch.stack(
        [into_x.query(yq.expand(P, -1, -1), o.expand(P, -1))[0].mean(dim=1) for yq, o in zip(y, y_orders)], dim=1
    )  # (P, Q)
    return factor * 0.5 * (accuracy + completeness)
