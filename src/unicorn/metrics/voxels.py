"""3D IoU on voxel grids of closed meshes.

Grid: ``resolution`` cells per axis over the cube ``[lo, hi]^3`` (default 32^3 over the unit cube
[-0.5, 0.5]^3, the frame of ShapeNet-NMR objects and of SoftRas/Kato's voxel IoU); cell ``(i, j, k)`` (indexed
x, y, z) has its centre at ``lo + (index + 0.5) * (hi - lo) / resolution``. A cell is occupied when its centre
is inside the mesh, decided by ray parity: a ray parallel to +z is cast through each (x, y) column of centres,
its crossings with every triangle are found in float64, and a centre is inside when an odd number of crossings
lies below it. The rays are shifted by a tiny irrational fraction of a cell so that they do not pass exactly
through mesh edges or vertices placed on "round" coordinates. Meshes must be closed (watertight); for
self-intersecting meshes parity counts regions covered an even number of times as outside.

Thin parts with no cell centre inside them vanish from a solid grid; pass ``surface_samples`` to also mark the
cells that contain area-uniform surface samples (closer to the surface-then-fill voxelisation of Kato et al.).
"""

from __future__ import annotations

import math

import torch

from ._checks import check_mesh
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


def _parity_occupancy(
    verts: torch.Tensor, faces: torch.Tensor, centres: torch.Tensor, jitter: tuple[float, float], block: int
) -> torch.Tensor:
    R = centres.shape[0]
    tri = verts[faces].double()  # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    # 2D barycentric setup in the xy plane; vertical faces (zero projected area) never count as crossings
    v0, v1 = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2]
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    keep = den.abs() > 1e-15
    a, b, c, v0, v1, den = a[keep], b[keep], c[keep], v0[keep], v1[keep], den[keep]
    occ = torch.zeros(R, R, R, dtype=torch.bool, device=verts.device)
    if den.numel() == 0:
        return occ
    xs = centres + jitter[0]
    ys = centres + jitter[1]
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    cols = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)  # (R*R, 2)
    rows = max(1, block // den.numel())
    counts = []
    for start in range(0, cols.shape[0], rows):
        p = cols[start : start + rows].unsqueeze(1) - a[:, :2].unsqueeze(0)  # (c, F, 2)
        u = (p[..., 0] * v1[:, 1] - v1[:, 0] * p[..., 1]) / den
        v = (v0[:, 0] * p[..., 1] - p[..., 0] * v0[:, 1]) / den
        hit = (u >= 0) & (v >= 0) & (u + v <= 1)
        z = a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2])
        z = torch.where(hit, z, torch.full_like(z, math.inf)).sort(dim=1).values
        below = torch.searchsorted(z, centres.unsqueeze(0).expand(z.shape[0], R).contiguous())  # (c, R)
        counts.append(below)
    occ = (torch.cat(counts) % 2 == 1).view(R, R, R)
    return occ


def voxelize_mesh(
    verts: torch.Tensor,
    faces: torch.Tensor,
    resolution: int = 32,
    bounds: tuple[float, float] = (-0.5, 0.5),
    *,
    surface_samples: int = 0,
    seed: int = 0,
    block_elements: int = 2**22,
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
        block_elements: largest (columns x faces) block of ray-triangle tests held at once.

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
    jitter = (step * 1.2345678e-6 * math.sqrt(2), step * 1.2345678e-6 * math.pi / 3)
    occ = torch.stack([_parity_occupancy(v.detach(), faces.long(), centres, jitter, block_elements) for v in verts])
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
