"""Template meshes and their spherical UV coordinates.

Meshes in unicorn share one topology across a batch: vertices (B, V, 3) float and faces (F, 3) long.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable

import torch
import trimesh

from unicorn.checks import check_faces, check_shape, is_real

__all__ = [
    "ellipsoid",
    "icosphere",
    "mirror_points",
    "mirror_spherical_map",
    "spherical_face_uvs",
    "spherical_vertex_uvs",
]


def icosphere(level: int = 3, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit icosphere: level 3 has 642 vertices and 1280 faces, level 4 has 2562 and 5120.

    Faces are counter-clockwise seen from outside (outward normals).

    Returns:
        verts: (V, 3) and faces: (F, 3) long.

    Raises:
        ValueError: ``level`` not a whole number in [0, 7] (3.0 is 3; 2.5 or True are errors).
        TypeError: ``dtype`` not a floating point torch dtype (an integer one would round the vertices).
    """
    # a bool is no level, and trimesh would subdivide a 2.5 twice without a word
    whole = isinstance(level, numbers.Real) and not isinstance(level, bool) and float(level).is_integer()
    if not (whole and 0 <= level <= 7):
        raise ValueError(f"icosphere level must be a whole number in [0, 7], got {level!r}")
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"icosphere dtype must be a floating point torch dtype, got {dtype!r}")
    mesh = trimesh.creation.icosphere(subdivisions=int(level), radius=1.0)
    verts = torch.as_tensor(mesh.vertices, dtype=dtype)
    faces = torch.as_tensor(mesh.faces, dtype=torch.long)
    return verts, faces


def ellipsoid(
    level: int = 3, axes: tuple[float, float, float] = (1.0, 0.7, 0.7), scale: float = 1.0, bottom: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Icosphere stretched by ``scale * axes`` (UNICORN's template: long axis X), its lower half (y < 0) squashed
    to ``bottom`` times its height (1: an ellipsoid; below 1: a dome on a flatter base, not up-down symmetric).

    Returns:
        verts: (V, 3) and faces: (F, 3) long.

    Raises:
        ValueError: ``level`` refused by :func:`icosphere`, ``axes`` not three finite numbers > 0, ``scale`` not a
            finite number > 0, or ``bottom`` not a number in (0, 1]. A zero or negative stretch would flatten the
            template or turn it inside out (its faces clockwise seen from outside).
    """
    values = list(axes) if isinstance(axes, Iterable) and not isinstance(axes, str) else []
    if not (len(values) == 3 and all(_positive(a) for a in values)):
        raise ValueError(f"ellipsoid axes must be three finite numbers > 0 (x, y, z), got {axes!r}")
    if not _positive(scale):
        raise ValueError(f"ellipsoid scale must be a finite number > 0, got {scale!r}")
    if not (_positive(bottom) and bottom <= 1):
        raise ValueError(f"ellipsoid bottom must be a number in (0, 1], got {bottom!r}")
    verts, faces = icosphere(level)
    verts = verts * torch.tensor([float(a) for a in values], dtype=verts.dtype) * float(scale)
    verts[:, 1] = torch.where(verts[:, 1] < 0, verts[:, 1] * float(bottom), verts[:, 1])
    return verts, faces


def _positive(value: object) -> bool:
    """Whether ``value`` is a finite real number > 0 (a bool is no number)."""
    return is_real(value) and math.isfinite(value) and value > 0


def spherical_vertex_uvs(verts: torch.Tensor) -> torch.Tensor:
    """UNICORN's per-vertex spherical UVs (V, 2): u from the azimuth about +Y (0.5 at +Z), v from +Y (0) to -Y (1).

    These are what the released checkpoints were trained with; they are discontinuous along the seam
    (x = 0, z < 0) and undefined at the poles. Use :func:`spherical_face_uvs` for rendering.

    Raises:
        unicorn.checks.ShapeError: ``verts`` is not (V, 3) floating point (a batch (B, V, 3) included: give one
            mesh's vertices).
    """
    check_shape(verts, "V, 3", "verts", floating=True)
    r = verts.norm(dim=-1).clamp_min(1e-5)
    theta = torch.acos((verts[:, 1] / r).clamp(-1 + 1e-5, 1 - 1e-5))
    phi = torch.atan2(verts[:, 0], verts[:, 2])
    return torch.stack([(phi + math.pi) / (2 * math.pi), theta / math.pi], dim=-1)


def spherical_face_uvs(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Per-face-vertex spherical UVs (F, 3, 2) with the seam and the poles handled.

    Faces that straddle the seam get ``u + 1`` on their vertices with ``u < 0.5``, so that ``u`` varies by less
    than half a turn inside every face; sample them with a horizontally periodic texture lookup
    (``TexturesUV(..., wrap_u=True)``). A pole vertex, whose azimuth is undefined, takes the mean ``u`` of the
    two other vertices of each face it belongs to.

    Args:
        verts: (V, 3) floating point vertices of one mesh.
        faces: (F, 3) integer vertex indices.

    Raises:
        unicorn.checks.ShapeError, TypeError, unicorn.checks.FaceIndexError: a batch of meshes, or faces not
            (F, 3) integer indices of ``verts``.
    """
    check_shape(verts, "V, 3", "verts", floating=True)
    check_faces(faces, verts.shape[0], allow_empty=True)
    uv = spherical_vertex_uvs(verts)[faces]  # (F, 3, 2)
    u = uv[..., 0]
    straddles = (u.max(dim=1).values - u.min(dim=1).values) > 0.5
    u = torch.where(straddles.unsqueeze(1) & (u < 0.5), u + 1.0, u)
    radial = verts[:, [0, 2]].norm(dim=-1)
    is_pole = (radial < 1e-6 * verts.norm(dim=-1).clamp_min(1e-12))[faces]  # (F, 3)
    if is_pole.any():
        others = (~is_pole).to(u.dtype)
        mean_other = (u * others).sum(1) / others.sum(1).clamp_min(1.0)
        u = torch.where(is_pole, mean_other.unsqueeze(1), u)
        # the two other vertices of a pole face may straddle the seam after all
        straddles = (u.max(dim=1).values - u.min(dim=1).values) > 0.5
        u = torch.where(straddles.unsqueeze(1) & (u < 0.5), u + 1.0, u)
    return torch.stack([u, uv[..., 1]], dim=-1)


# The template's mirror plane is z = 0, the plane of its long axis (X) and its up axis (Y): with the model's symmetry
# prior on (unicorn.model.field.ShapeHead, unicorn.model.generator.CodeGenerator), a learned canonical frame must put
# an object's own plane of symmetry there (a car's length, a mug's handle along X).


def mirror_points(points: torch.Tensor) -> torch.Tensor:
    """Mirror points (..., 3) through the template's plane of symmetry z = 0.

    Raises:
        unicorn.checks.ShapeError: ``points`` not of shape (..., 3).
    """
    check_shape(points, "*, 3", "points")
    return points * points.new_tensor((1.0, 1.0, -1.0))


def mirror_spherical_map(maps: torch.Tensor) -> torch.Tensor:
    """Mirror texture maps (..., H, W) sampled through :func:`spherical_vertex_uvs` with a horizontally wrapping,
    texel-centred lookup (``TexturesUV(wrap_u=True)``), so that the mirrored map seen at a point shows what the
    map shows at its mirror image (:func:`mirror_points`).

    Mirroring z flips the azimuth ``atan2(x, z)`` about the X axis, ``u -> 0.5 - u`` (mod 1): texel column ``j``
    (centre ``(j + 0.5) / W``) takes column ``W/2 - 1 - j`` (mod W). ``W`` must be even.
    """
    width = maps.shape[-1]
    if width % 2:
        raise ValueError(f"a spherical texture map needs an even width to be mirrored, got {width}")
    return torch.roll(maps.flip(-1), width // 2, dims=-1)
