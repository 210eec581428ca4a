"""Camera pose errors: geodesic rotation error, azimuth error, and canonical-frame alignment.

Rotations are world-to-view in unicorn's row-vector convention (``x_view = x @ R + T``). An unsupervised model
learns its own canonical object frame, related to the ground-truth frame by one fixed rotation ``Q``:
``x_learned = x_gt @ Q`` so that ``R_gt = Q @ R_pred`` for every image. :func:`align_canonical_frame`
estimates ``Q`` over a test set before the per-image errors are measured (as is standard for viewpoint metrics
of unsupervised methods); without alignment the errors assume the learned axes already match the ground truth.
"""

from __future__ import annotations

import math

import torch

from unicorn.checks import check_rotations, check_shape

from ..geometry.rotations import rotation_angle_between
from .instance import flip_rate, rotation_accuracy

__all__ = [
    "align_canonical_frame",
    "azimuth_error",
    "geodesic_error",
    "pose_errors",
    "rotation_to_azim_elev_roll",
]


def geodesic_error(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in degrees, in [0, 180], between rotations (..., 3, 3).

    The metric name for :func:`unicorn.geometry.rotations.rotation_angle_between` (atan2 form, accurate near
    0 and 180 degrees). Equal to scipy's ``Rotation.magnitude`` of ``R1^T R2`` (the tests check it), but kept in
    torch: it runs batched on the model's device inside training (neighbour matching) and evaluation, where a
    round trip through scipy's CPU float64 arrays would cost a copy per call; kornia has no such distance.

    Example:
        >>> Rz = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        >>> round(geodesic_error(torch.eye(3), Rz).item(), 4)
        90.0
    """
    return rotation_angle_between(R1, R2)


def azimuth_error(azim_pred: torch.Tensor, azim_gt: torch.Tensor) -> torch.Tensor:
    """Absolute azimuth difference in degrees, wrapped to [0, 180].

    Example:
        >>> azimuth_error(torch.tensor([350.0, 10.0]), torch.tensor([10.0, 200.0])).tolist()
        [20.0, 170.0]
    """
    diff = torch.remainder(azim_pred - azim_gt.to(azim_pred) + 180.0, 360.0) - 180.0
    return diff.abs()


def rotation_to_azim_elev_roll(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse of :func:`unicorn.geometry.rotations.azim_elev_roll_to_rotation`.

    Args:
        R: (..., 3, 3) rotations ``Az(azim) @ El(elev) @ Ro(roll)``.

    Returns:
        azim in (-180, 180], elev in [-90, 90], roll in (-180, 180], each (...) in degrees (azimuth and roll
        are undefined at elevation +-90).
    """
    check_shape(R, "*, 3, 3", "R")
    azim = torch.rad2deg(torch.atan2(R[..., 0, 2], R[..., 2, 2]))
    # atan2, not asin(-R[1, 2]): as accurate near +-90 as elsewhere (asin reads float32's 89.99 degrees as 90)
    elev = torch.rad2deg(torch.atan2(-R[..., 1, 2], torch.hypot(R[..., 0, 2], R[..., 2, 2])))
    roll = torch.rad2deg(torch.atan2(-R[..., 1, 0], R[..., 1, 1]))
    return azim, elev, roll


def _kabsch(M: torch.Tensor) -> torch.Tensor:
    """The rotation Q maximising ``tr(Q^T M)`` for (..., 3, 3) ``M``.

    Written out (three lines of SVD) because it is applied to a batch of summed rotation matrices, not to the
    paired vectors that scipy's ``Rotation.align_vectors`` takes.
    """
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    return U @ D @ Vh


def _median(values: torch.Tensor) -> float:
    """The median of ``values`` (N,), the mean of the two middle ones for an even N (``torch.median`` gives the
    lower one)."""
    return float(torch.quantile(values.double(), 0.5))


def _median_errors(Q: torch.Tensor, R_pred: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    """Median over samples of the error of each candidate Q (C, 3, 3) -> (C,)."""
    out = []
    for q in Q.split(64):
        err = geodesic_error(q.unsqueeze(1) @ R_pred.unsqueeze(0), R_gt.unsqueeze(0))  # (c, N)
        out.append(err.median(dim=1).values)
    return torch.cat(out)


def align_canonical_frame(
    R_pred: torch.Tensor, R_gt: torch.Tensor, *, max_candidates: int = 256, refine_steps: int = 10
) -> torch.Tensor:
    """The global rotation ``Q`` making ``Q @ R_pred`` closest to ``R_gt`` in median geodesic error.

    Candidates are the chordal least-squares solution (Kabsch/Procrustes on ``sum_i R_gt_i R_pred_i^T``) and
    the per-image relative rotations ``R_gt_i R_pred_i^T`` of up to ``max_candidates`` evenly spaced images
    (each one aligns its image exactly, so a frame that is right for most images is among them even when a
    large share of predictions is flipped); the candidate with the lowest median error is kept and then
    refined by Kabsch on the images whose error is at most the median, for as long as that lowers the median.

    Args:
        R_pred: (N, 3, 3) predicted rotations.
        R_gt: (N, 3, 3) ground-truth rotations.
        max_candidates: per-image candidates tried.
        refine_steps: most inlier-Kabsch refinements.

    Returns:
        (3, 3) rotation ``Q``, dtype of ``R_pred``.
    """
    check_rotations(R_pred, "R_pred")
    check_rotations(R_gt, "R_gt", R_pred.shape[0])
    dtype = R_pred.dtype
    R_pred, R_gt = R_pred.double(), R_gt.to(R_pred.device).double()
    N = R_pred.shape[0]
    relative = R_gt @ R_pred.transpose(1, 2)  # (N, 3, 3), each aligns one image
    pick = torch.linspace(0, N - 1, min(N, max_candidates), device=R_pred.device).round().long().unique()
    candidates = torch.cat([_kabsch(relative.sum(0)).unsqueeze(0), relative[pick]])
    medians = _median_errors(candidates, R_pred, R_gt)
    best = int(medians.argmin())
    Q, best_median = candidates[best], medians[best]
    for _ in range(refine_steps):
        err = geodesic_error(Q @ R_pred, R_gt)
        inliers = err <= err.median()
        Q_new = _kabsch(relative[inliers].sum(0))
        new_median = _median_errors(Q_new.unsqueeze(0), R_pred, R_gt)[0]
        if not new_median < best_median:
            break
        Q, best_median = Q_new, new_median
    return Q.to(dtype)


def _degrees(value: float) -> str:
    """A threshold as it appears in a metric's key: ``30`` rather than ``30.0``."""
    return str(round(value)) if math.isclose(value, round(value)) else f"{value:g}"


def pose_errors(
    R_pred: torch.Tensor,
    R_gt: torch.Tensor,
    *,
    align: bool = False,
    accuracy_threshold: float = 30.0,
    flip_threshold: float = 150.0,
) -> dict[str, float]:
    """Summary of rotation and azimuth errors over a test set.

    Args:
        R_pred: (N, 3, 3) predicted world-to-view rotations.
        R_gt: (N, 3, 3) ground-truth rotations.
        align: first map the learned canonical frame to the ground truth with :func:`align_canonical_frame`
            (needs N >= 2: one view is aligned exactly).
        accuracy_threshold: degrees for the accuracy ratio (30 = pi / 6, the standard Acc_{pi/6}).
        flip_threshold: degrees above which an image counts as predicted turned round (flipped).

    Returns:
        ``rot-err-mean``, ``rot-err-median`` (degrees), ``rot-acc-30`` (fraction of images below the
        accuracy threshold, :func:`~unicorn.metrics.instance.rotation_accuracy`), ``rot-flip-150`` (fraction
        above the flip threshold, :func:`~unicorn.metrics.instance.flip_rate`; the keys follow the thresholds),
        ``azim-err-mean`` and ``azim-err-median`` (degrees, azimuths read with
        :func:`rotation_to_azim_elev_roll`).

    Raises:
        ValueError: no rotations, or ``align`` with a single one.
    """
    check_rotations(R_pred, "R_pred")
    check_rotations(R_gt, "R_gt", R_pred.shape[0])
    if R_pred.shape[0] == 0:
        raise ValueError("need at least one rotation")
    if align and R_pred.shape[0] < 2:  # the rotation aligning one view makes its error 0 whatever the prediction
        raise ValueError(f"aligning the canonical frame needs at least 2 rotations, got {R_pred.shape[0]}")
    R_gt = R_gt.to(R_pred)
    if align:
        R_pred = align_canonical_frame(R_pred, R_gt).to(R_pred) @ R_pred
    err = geodesic_error(R_pred, R_gt)
    azim_err = azimuth_error(rotation_to_azim_elev_roll(R_pred)[0], rotation_to_azim_elev_roll(R_gt)[0])
    return {
        "rot-err-mean": float(err.mean()),
        "rot-err-median": _median(err),
        f"rot-acc-{_degrees(accuracy_threshold)}": rotation_accuracy(err, accuracy_threshold),
        f"rot-flip-{_degrees(flip_threshold)}": flip_rate(err, flip_threshold),
        "azim-err-mean": float(azim_err.mean()),
        "azim-err-median": _median(azim_err),
    }
