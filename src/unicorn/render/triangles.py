"""2D triangle geometry of the rasterizer: barycentrics and squared distances to a triangle's boundary.

Triangles are (N, 3, 2) in pixel units (column, row); points are (N,) ``px``, ``py`` paired with them.
"""

from __future__ import annotations

import torch

__all__ = [
    "barycentric",
    "barycentric_and_distance",
    "barycentric_coefficients",
    "boundary_distance2",
    "clip_barycentric",
    "covered_barycentric",
    "perspective_correct_barycentric",
]


def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def barycentric(tri: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Unclipped screen-space barycentrics (N, 3) of points (px, py) in 2D triangles (N, 3, 2)."""
    x0, x1, x2 = tri[..., 0].unbind(-1)
    y0, y1, y2 = tri[..., 1].unbind(-1)
    area = _edge(x0, y0, x1, y1, x2, y2).unsqueeze(-1)
    w = torch.stack([_edge(x1, y1, x2, y2, px, py), _edge(x2, y2, x0, y0, px, py), _edge(x0, y0, x1, y1, px, py)], -1)
    return w / area


def barycentric_coefficients(tri: torch.Tensor) -> torch.Tensor:
    """(N, 18) coefficients of the 2D triangles (N, 3, 2) for :func:`covered_barycentric`, six groups of three
    (one per vertex i and the edge opposite it):

    - ``A, B, xp, yp``: the edge's line function ``e_i = A_i (x - xp_i) + B_i (y - yp_i)`` from its first endpoint
      ``(xp, yp)``, its endpoints taken in a fixed order (the lesser by (x, y) first), so that two triangles sharing
      an edge compute the same ``e_i`` at every point, and ``e_i`` is exactly 0 at both endpoints (a vertex on a
      pixel centre lies on each of its edges, not a rounding error off some of them);
    - ``k``: the factor (+-1 over twice the signed area; 0 for a degenerate triangle) making ``k_i e_i`` the
      barycentric ``w_i``;
    - ``t``: 1 where the triangle owns the points exactly on that edge, else 0: those whose interior lies toward
      +x (the next column) of the edge, toward +y (the next row) for an edge along x. Of two triangles on either
      side of an edge, exactly one owns it, as if every point were moved by an infinitesimal step along +x, then
      +y.
    """
    x, y = tri[..., 0], tri[..., 1]
    xj, yj = x.roll(-1, dims=-1), y.roll(-1, dims=-1)  # vertex i's opposite edge runs from j = i+1 to k = i+2
    xk, yk = x.roll(-2, dims=-1), y.roll(-2, dims=-1)
    swap = (xk < xj) | ((xk == xj) & (yk < yj))  # the edge's fixed order: from (xp, yp) to (xq, yq)
    xp, yp = torch.where(swap, xk, xj), torch.where(swap, yk, yj)
    xq, yq = torch.where(swap, xj, xk), torch.where(swap, yj, yk)
    a, b = -(yq - yp), xq - xp
    area = _edge(x[..., 0], y[..., 0], x[..., 1], y[..., 1], x[..., 2], y[..., 2]).unsqueeze(-1)
    sign = torch.where(swap, -1.0, 1.0).to(area.dtype)
    k = torch.where(area != 0, sign / area, torch.zeros_like(area))
    owns = (k * a > 0) | ((a == 0) & (k * b > 0))
    return torch.cat([a, b, xp, yp, k, owns.to(k.dtype)], dim=-1)


def covered_barycentric(
    coef: torch.Tensor, face: torch.Tensor, px: torch.Tensor, py: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unclipped barycentrics (P, 3) of the points (P, 1) ``px``, ``py`` in their triangles ``face`` (P,), indices
    into the triangles' :func:`barycentric_coefficients` ``coef`` (N, 18), and whether each point is covered (P,):
    inside, or on an edge its triangle owns. A point on an edge two triangles share is covered by exactly one.
    """
    # gathered three columns at a time and combined in place: (P, 3) tensors are the largest of the rasterizer
    a, b = coef[:, :3].index_select(0, face), coef[:, 3:6].index_select(0, face)
    dx = torch.sub(px, coef[:, 6:9].index_select(0, face))
    far = dx == b  # at the edge's far end (dx, dy) = (B, -A): e = -(A B) + B A is 0, kept so where a compiler
    e = dx.mul_(a)  # would fuse the products (a fused multiply-add leaves A B's rounding error)
    dy = torch.sub(py, coef[:, 9:12].index_select(0, face))
    far &= dy == a.neg_()
    e.add_(dy.mul_(b)).masked_fill_(far, 0.0)
    del a, b, dy, far
    k = coef[:, 12:15].index_select(0, face)
    on_owned = (e == 0) & (coef[:, 15:] > 0).index_select(0, face)
    bary = e.mul_(k)
    return bary, ((bary > 0) | on_owned).all(-1)


def _segment_distance2(px, py, ax, ay, bx, by):
    """Squared distance from points to segments [a, b], the segment parameter clamped to [0, 1]."""
    ex, ey = bx - ax, by - ay
    dx, dy = px - ax, py - ay
    t = ((dx * ex + dy * ey) / (ex * ex + ey * ey).clamp_min(1e-20)).clamp(0.0, 1.0)
    return (dx - t * ex) ** 2 + (dy - t * ey) ** 2


def boundary_distance2(tri: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Squared distance (N,) from points to the boundary of 2D triangles (N, 3, 2)."""
    x0, x1, x2 = tri[..., 0].unbind(-1)
    y0, y1, y2 = tri[..., 1].unbind(-1)
    d01 = _segment_distance2(px, py, x0, y0, x1, y1)
    d12 = _segment_distance2(px, py, x1, y1, x2, y2)
    d20 = _segment_distance2(px, py, x2, y2, x0, y0)
    return torch.minimum(torch.minimum(d01, d12), d20)


def barycentric_and_distance(
    tri: torch.Tensor, px: torch.Tensor, py: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unclipped barycentrics (N, 3) and squared distance (N,) to the boundary of 2D triangles (N, 3, 2)."""
    return barycentric(tri, px, py), boundary_distance2(tri, px, py)


def perspective_correct_barycentric(bary: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Screen-space barycentrics (N, 3) to those of the 3D point seen there, for triangles whose corners have the
    view depths ``z`` (N, 3), all > 0: ``(b_i / z_i) / sum_j (b_j / z_j)``, as PyTorch3D's ``perspective_correct``.

    Computed as ``b_i z_j z_k / sum(...)`` with the denominator clamped to >= 1e-8 (PyTorch3D's), which only a
    point far outside its face, beyond the horizon of the face's plane, can reach. Signs are kept: a point inside
    its face (every ``b_i > 0``) stays inside.
    """
    z0, z1, z2 = z.unbind(-1)
    weighted = bary * torch.stack([z1 * z2, z2 * z0, z0 * z1], -1)
    return weighted / weighted.sum(-1, keepdim=True).clamp_min(1e-8)


def clip_barycentric(bary: torch.Tensor) -> torch.Tensor:
    """Barycentrics (N, 3) clamped to >= 0 and renormalised to sum to 1 (a point of the triangle), as PyTorch3D's
    ``clip_barycentric_coordinates``: depth and attributes at a near-miss pixel are read on the face."""
    clipped = bary.clamp_min(0.0)
    return clipped / clipped.sum(-1, keepdim=True).clamp_min(1e-5)
