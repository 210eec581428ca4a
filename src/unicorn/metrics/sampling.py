"""Area-weighted uniform point sampling on triangle meshes, with face normals."""

from __future__ import annotations

import torch

from unicorn.checks import check_limit, check_mesh

__all__ = ["MAX_POINTS", "check_point_count", "face_areas_normals", "sample_points_from_meshes"]

#: the most points sampled on one mesh (evaluation's ``num_points`` and ``shape_points``, the synthetic set's
#: ground-truth points): 100 times UNICORN's evaluation protocol (100k)
MAX_POINTS = 10_000_000


def check_point_count(setting: str, n: int) -> None:
    """Refuse more than :data:`MAX_POINTS` points per mesh before they are sampled.

    Raises:
        unicorn.checks.SizeLimitError: the message names ``setting`` (e.g. ``"--num-points 10000000000"``).
    """
    check_limit(setting, "points sampled on each mesh", n, MAX_POINTS, "points", "unicorn.metrics.MAX_POINTS")


def face_areas_normals(verts: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Areas and unit normals of the faces of a batch of meshes sharing one topology.

    Args:
        verts: (B, V, 3) float vertices.
        faces: (F, 3) long vertex indices, counter-clockwise seen from outside for outward normals.

    Returns:
        areas: (B, F) face areas.
        normals: (B, F, 3) unit face normals (zero for degenerate faces).
    """
    check_mesh(verts, faces)
    tri = verts[:, faces.long()]  # (B, F, 3, 3)
    cross = torch.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    norm = torch.linalg.vector_norm(cross, dim=-1)
    normals = cross / norm.clamp_min(torch.finfo(verts.dtype).tiny).unsqueeze(-1)
    normals = torch.where((norm > 0).unsqueeze(-1), normals, torch.zeros_like(normals))
    return 0.5 * norm, normals


def sample_points_from_meshes(
    verts: torch.Tensor,
    faces: torch.Tensor,
    num_samples: int,
    *,
    seed: int | None = None,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample points uniformly by area on each mesh of a batch, with the normal of the face each lies on.

    Faces are drawn with probability proportional to their area (with replacement) and a point is drawn
    uniformly in each drawn triangle (``u = 1 - sqrt(r1)``, ``v = sqrt(r1) (1 - r2)``, ``w = sqrt(r1) r2``).
    The random numbers are drawn on the CPU, so a given ``seed`` gives the same samples on every device. A
    mesh whose faces all have zero area is sampled uniformly over its faces and gets zero normals. Points are
    differentiable w.r.t. ``verts``.

    Args:
        verts: (B, V, 3) float vertices (or (V, 3) for a single mesh).
        faces: (F, 3) long vertex indices shared by the batch.
        num_samples: N, points per mesh (>= 1).
        seed: seed of a private CPU generator; ignored when ``generator`` is given.
        generator: a CPU :class:`torch.Generator` to draw from; the global RNG when both are None.

    Returns:
        points: (B, N, 3) sampled points (or (N, 3) for an unbatched input).
        normals: (B, N, 3) unit normals of the faces the points lie on, same batching as ``points``.

    Example:
        >>> import trimesh
        >>> box = trimesh.creation.box()
        >>> v = torch.tensor(box.vertices, dtype=torch.float32)
        >>> p, n = sample_points_from_meshes(v, torch.tensor(box.faces), 1000, seed=0)
        >>> p.shape, bool((p.abs().max(-1).values - 0.5).abs().max() < 1e-6)
        (torch.Size([1000, 3]), True)
    """
    unbatched = isinstance(verts, torch.Tensor) and verts.dim() == 2
    if unbatched:
        verts = verts.unsqueeze(0)
    if not isinstance(num_samples, int) or num_samples < 1:
        raise ValueError(f"num_samples must be a positive int, got {num_samples!r}")
    if generator is None and seed is not None:
        generator = torch.Generator().manual_seed(int(seed))
    if generator is not None and generator.device.type != "cpu":
        raise ValueError("generator must be a CPU generator (samples are drawn on the CPU for reproducibility)")
    areas, normals = face_areas_normals(verts, faces)
    B, F = areas.shape
    weights = areas.detach().to(device="cpu", dtype=torch.float64)
    empty = weights.sum(dim=1) <= 0
    weights[empty] = 1.0
    face_idx = torch.multinomial(weights, num_samples, replacement=True, generator=generator)  # (B, N)
    r = torch.rand(B, num_samples, 2, generator=generator, dtype=torch.float64)
    face_idx = face_idx.to(verts.device)
    r = r.to(device=verts.device, dtype=verts.dtype)
    s1 = r[..., 0].sqrt()
    bary = torch.stack([1 - s1, s1 * (1 - r[..., 1]), s1 * r[..., 1]], dim=-1)  # (B, N, 3)
    batch_idx = torch.arange(B, device=verts.device).view(B, 1, 1)
    tri_verts = verts[batch_idx, faces.long()[face_idx]]  # (B, N, 3, 3)
    points = (bary.unsqueeze(-1) * tri_verts).sum(dim=2)
    point_normals = torch.gather(normals, 1, face_idx.unsqueeze(-1).expand(-1, -1, 3))
    if unbatched:
        return points[0], point_normals[0]
    return points, point_normals
