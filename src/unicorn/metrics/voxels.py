"""3D IoU on voxel grids of closed meshes.

Grid: ``resolution`` cells per axis over the cube ``[lo, hi]^3`` (default 32^3 over the unit cube
[-0.5, 0.5]^3, the frame of ShapeNet-NMR objects and of SoftRas/Kato's voxel IoU); cell ``(i, j, k)`` (indexed
x, y, z) has its centre at ``lo + (index + 0.5) * (hi - lo) / resolution``. A cell is occupied when its centre
is inside the mesh, decided by ray parity with open3d's ``RaycastingScene.compute_occupancy`` (Embree; float32,
about 25 times faster than a float64 torch ray caster, with identical grids on the test meshes). Meshes must
be closed (watertight); for self-intersecting meshes parity counts regions covered an
even number of times as outside. No gradient flows through occupancy, so nothing here needs torch.

Thin parts with no cell centre inside them vanish from a solid grid; pass ``surface_samples`` to also mark the
cells that contain area-uniform surface samples (closer to the surface-then-fill voxelisation of Kato et al.).
"""

from __future__ import annotations

import numpy as np
import torch

from unicorn.checks import check_mesh

from .sampling import sample_points_from_meshes

__all__ = ["mesh_voxel_iou", "voxel_centers", "voxel_iou", "voxelize_mesh"]


def voxel_centers(
    resolution: int = 32,
    bounds: tuple[float, float] = (-0.5, 0.5),
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Centres (R,) of the cells along one axis: ``lo + (arange(R) + 0.5) * (hi - lo) / R``."""
    lo, hi = bounds
    if resolution < 1 or not hi > lo:
        raise ValueError(f"need resolution >= 1 and hi > lo, got {resolution} and {bounds}")
    step = (hi - lo) / resolution
    return lo + (torch.arange(resolution, dtype=dtype, device=device) + 0.5) * step


def _occupancy(verts: torch.Tensor, faces: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """(R, R, R) bool: which cell centres (the grid of ``centres`` (R,) per axis) lie inside one closed mesh."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(verts.detach().cpu().numpy().astype(np.float32)),
        o3d.core.Tensor(faces.cpu().numpy().astype(np.uint32)),
    )
    c = centres.cpu().numpy()
    grid = np.stack(np.meshgrid(c, c, c, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
    inside = scene.compute_occupancy(o3d.core.Tensor(grid)).numpy().astype(bool)
    R = c.shape[0]
    return torch.from_numpy(inside.reshape(R, R, R)).to(verts.device)


def voxelize_mesh(
    verts: torch.Tensor,
    faces: torch.Tensor,
    resolution: int = 32,
    bounds: tuple[float, float] = (-0.5, 0.5),
    *,
    surface_samples: int = 0,
    seed: int = 0,
) -> torch.Tensor:
    """Solid occupancy grids of closed meshes (cell centres inside the mesh, by ray parity).

    Args:
        verts: (B, V, 3) or (V, 3) vertices in the grid's frame.
        faces: (F, 3) long faces shared by the batch.
        resolution: R, cells per axis.
        bounds: (lo, hi) of the cube covered by the grid.
        surface_samples: if > 0, also mark the cells containing that many area-uniform surface samples per
            mesh.
        seed: seed of the surface samples.

    Returns:
        (B, R, R, R) bool occupancy indexed [x, y, z] (or (R, R, R) for an unbatched input).

    Example:
        >>> import trimesh
        >>> box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
        >>> occ = voxelize_mesh(torch.tensor(box.vertices), torch.tensor(box.faces), resolution=8)
        >>> int(occ.sum())  # the central 4 x 4 x 4 cells
        64
    """
    unbatched = isinstance(verts, torch.Tensor) and verts.dim() == 2
    if unbatched:
        verts = verts.unsqueeze(0)
    check_mesh(verts, faces)
    centres = voxel_centers(resolution, bounds, dtype=torch.float64, device=verts.device)
    step = (bounds[1] - bounds[0]) / resolution
    occ = torch.stack([_occupancy(v, faces, centres) for v in verts])
    if surface_samples > 0:
        points, _ = sample_points_from_meshes(verts.detach(), faces, surface_samples, seed=seed)
        idx = torch.floor((points.double() - bounds[0]) / step).long()
        inside = ((idx >= 0) & (idx < resolution)).all(dim=-1)
        for b in range(occ.shape[0]):
            i = idx[b][inside[b]]
            occ[b, i[:, 0], i[:, 1], i[:, 2]] = True
    return occ[0] if unbatched else occ


def voxel_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU ``|a & b| / |a | b|`` of occupancy grids (B, R, R, R) (or (R, R, R)); 1 when both are empty.

    Example:
        >>> a = torch.zeros(4, 4, 4, dtype=torch.bool); a[:2] = True
        >>> b = torch.zeros(4, 4, 4, dtype=torch.bool); b[1:3] = True
        >>> round(voxel_iou(a, b).item(), 4)
        0.3333
    """
    if a.shape != b.shape or a.dim() not in (3, 4):
        raise ValueError(f"grids must share a shape (B, R, R, R) or (R, R, R), got {tuple(a.shape)}, {tuple(b.shape)}")
    a, b = a.bool(), b.to(a.device).bool()
    dims = tuple(range(a.dim() - 3, a.dim()))
    inter = (a & b).sum(dim=dims).double()
    union = (a | b).sum(dim=dims).double()
    return torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union))


def mesh_voxel_iou(
    verts_pred: torch.Tensor,
    faces_pred: torch.Tensor,
    verts_gt: torch.Tensor,
    faces_gt: torch.Tensor,
    resolution: int = 32,
    bounds: tuple[float, float] = (-0.5, 0.5),
    *,
    surface_samples: int = 0,
) -> torch.Tensor:
    """3D IoU of predicted and ground-truth closed meshes on a shared grid (see :func:`voxelize_mesh`).

    Args:
        verts_pred: (B, V, 3) predicted vertices, in the ground-truth frame (align them first).
        faces_pred: (F, 3) predicted faces.
        verts_gt: (B, V', 3) ground-truth vertices.
        faces_gt: (F', 3) ground-truth faces.
        resolution: cells per axis (32 by default).
        bounds: cube covered by the grid.
        surface_samples: also mark cells containing surface samples, see :func:`voxelize_mesh`.

    Returns:
        (B,) float64 IoU.
    """
    pred = voxelize_mesh(verts_pred, faces_pred, resolution, bounds, surface_samples=surface_samples)
    gt = voxelize_mesh(verts_gt, faces_gt, resolution, bounds, surface_samples=surface_samples)
    return voxel_iou(pred, gt)
