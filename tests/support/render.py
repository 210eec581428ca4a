"""Scenes shared by the renderer tests: posed ellipsoids, random rotations, a textured template scene."""

from __future__ import annotations

import torch

from unicorn.geometry.mesh import ellipsoid, icosphere, spherical_face_uvs
from unicorn.geometry.rotations import euler_angles_to_matrix, look_at_view_transform


def random_rotations(n: int, generator: torch.Generator, dtype=torch.float32) -> torch.Tensor:
    angles = (torch.rand(n, 3, generator=generator, dtype=torch.float64) * 2 - 1) * torch.pi
    return euler_angles_to_matrix(angles, "ZYX").to(dtype)


def posed_ellipsoids(batch: int = 4, level: int = 2, dtype=torch.float32, seed: int = 0):
    """Randomly rotated and stretched ellipsoids seen from random viewpoints (verts, faces, R, T)."""
    g = torch.Generator().manual_seed(seed)
    v, f = icosphere(level, dtype=torch.float64)
    axes = 0.3 + 0.4 * torch.rand(batch, 1, 3, generator=g, dtype=torch.float64)
    verts = (v[None] * axes) @ random_rotations(batch, g, torch.float64)
    verts = verts + 0.1 * (torch.rand(batch, 1, 3, generator=g, dtype=torch.float64) - 0.5)
    R, T = look_at_view_transform(
        dist=2.2 + torch.rand(batch, generator=g, dtype=torch.float64),
        elev=60 * (torch.rand(batch, generator=g, dtype=torch.float64) - 0.5),
        azim=360 * torch.rand(batch, generator=g, dtype=torch.float64),
    )
    return verts.to(dtype), f, R.to(dtype), T.to(dtype)


def template_scene(batch: int = 2, level: int = 3, dtype=torch.float32):
    """UNICORN's ellipsoid template around the turntable, with UVs."""
    v, f = ellipsoid(level, scale=0.6)
    R, T = look_at_view_transform(2.732, 30.0, torch.arange(batch, dtype=torch.float64) * 360.0 / batch)
    return (
        v[None].repeat(batch, 1, 1).to(dtype),
        f,
        R.to(dtype),
        T.to(dtype),
        spherical_face_uvs(v, f).to(dtype),
    )
