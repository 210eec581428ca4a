"""Bringing predicted shapes into the ground-truth frame before scoring them.

- :func:`align_with_gt_pose`: a prediction expressed in its predicted camera pose is mapped into the
  ground-truth object frame with ``x_gt = (x_pred @ R_pred + T_pred - T_gt) @ R_gt^T`` (both poses
  world-to-view, ``x_view = x_world @ R + T``), so that shapes are compared where the camera puts them.
- :func:`normalize_to_unit_cube`: centre each shape on its bounding-box centre and scale it isotropically so
  that its largest absolute coordinate is 0.5, the frame of the ShapeNet ground-truth point clouds ([-0.5,
  0.5]^3), before the ICP branch of the evaluation.
"""

from __future__ import annotations

import torch

from unicorn.checks import check_points, check_rotations, check_translations

__all__ = ["align_with_gt_pose", "normalize_to_unit_cube"]


def align_with_gt_pose(
    verts: torch.Tensor,
    R_pred: torch.Tensor,
    T_pred: torch.Tensor,
    R_gt: torch.Tensor,
    T_gt: torch.Tensor,
) -> torch.Tensor:
    """Map predicted shapes into the ground-truth object frame through the camera frame.

    Args:
        verts: (B, V, 3) predicted vertices (or points) in the predicted object frame.
        R_pred: (B, 3, 3) predicted world-to-view rotations (``x_view = x @ R + T``).
        T_pred: (B, 3) predicted translations.
        R_gt: (B, 3, 3) ground-truth rotations in the same convention.
        T_gt: (B, 3) ground-truth translations.

    Returns:
        (B, V, 3) ``(verts @ R_pred + T_pred - T_gt) @ R_gt^T``.

    Example:
        >>> R = torch.eye(3)[None]
        >>> T = torch.tensor([[0.0, 0.0, 2.0]])
        >>> align_with_gt_pose(torch.ones(1, 1, 3), R, T, R, T).tolist()
        [[[1.0, 1.0, 1.0]]]
    """
    check_points(verts, "verts")
    B = verts.shape[0]
    for name, R in (("R_pred", R_pred), ("R_gt", R_gt)):
        check_rotations(R, name, B)
    for name, T in (("T_pred", T_pred), ("T_gt", T_gt)):
        check_translations(T, name, B)
    view = verts @ R_pred.to(verts) + T_pred.to(verts).unsqueeze(1)
    return (view - T_gt.to(verts).unsqueeze(1)) @ R_gt.to(verts).transpose(1, 2)


def normalize_to_unit_cube(
    verts: torch.Tensor, half_extent: float = 0.5
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centre each shape on its bounding-box centre and scale it so that ``max |coord| = half_extent``.

    Args:
        verts: (B, V, 3) vertices or points.
        half_extent: target largest absolute coordinate, 0.5 for the unit cube [-0.5, 0.5]^3.

    Returns:
        normalized: (B, V, 3) ``(verts - centre) * scale``.
        centre: (B, 3) bounding-box centres.
        scale: (B,) isotropic scale factors (1 for shapes collapsed to a point).

    Example:
        >>> v = torch.tensor([[[0.0, 0.0, 0.0], [4.0, 2.0, 1.0]]])
        >>> normalize_to_unit_cube(v)[0].tolist()
        [[[-0.5, -0.25, -0.125], [0.5, 0.25, 0.125]]]
    """
    check_points(verts, "verts")
    if not half_extent > 0:
        raise ValueError(f"half_extent must be positive, got {half_extent}")
    centre = 0.5 * (verts.amin(dim=1) + verts.amax(dim=1))
    centred = verts - centre.unsqueeze(1)
    extent = centred.abs().amax(dim=(1, 2))
    scale = torch.where(extent > 0, half_extent / extent.clamp_min(torch.finfo(verts.dtype).tiny), 1.0)
    return centred * scale.view(-1, 1, 1), centre, scale
