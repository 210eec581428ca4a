"""The template mesh every prediction deforms: an icosphere stretched into an ellipsoid, with UVs."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from unicorn.geometry.mesh import ellipsoid, spherical_face_uvs, spherical_vertex_uvs

__all__ = ["TemplateMesh", "UV_MODES"]

#: ``"seamless"``: per-face UVs with the seam and poles fixed, sampled with a horizontally wrapping lookup.
#: ``"reference"``: the released checkpoints' per-vertex UVs (seam faces interpolate across the whole map),
#: sampled with ``align_corners=True`` and border padding, to reproduce their predictions exactly.
UV_MODES = ("seamless", "reference")


class TemplateMesh(nn.Module):
    """Icosphere of the given level scaled by ``scale * axes`` (UNICORN: axes (1, 0.7), scale 0.6 / 0.4), its lower half
    squashed by ``bottom``.

    All tensors are derived from the configuration, so they are non-persistent buffers (they follow
    ``.to(device)`` but stay out of the state dict).

    Args:
        level: icosphere subdivision level (3: 642 vertices, 1280 faces).
        axes: anisotropic stretch, long axis X.
        scale: global scale (0.6 for real-image datasets, 0.4 for ShapeNet).
        uv_mode: one of :data:`UV_MODES`.
        bottom: the lower half's height as a share of the upper half's (1: the paper's ellipsoid; below 1: a dome
            on a flatter base, which is not up-down symmetric).

    Raises:
        ValueError: ``uv_mode`` not one of :data:`UV_MODES`, or ``level``, ``axes``, ``scale`` or ``bottom`` refused
            by :func:`unicorn.geometry.mesh.ellipsoid` (a level that is no whole number in [0, 7], a stretch that is
            not finite and > 0, a bottom outside (0, 1]).

    Attributes:
        verts: (V, 3) template vertices.
        faces: (F, 3) long, counter-clockwise seen from outside.
        vertex_uvs: (V, 2) reference per-vertex UVs.
        face_uvs: (F, 3, 2) per-face-vertex UVs used for rendering (depends on ``uv_mode``).
    """

    verts: torch.Tensor
    faces: torch.Tensor
    vertex_uvs: torch.Tensor
    face_uvs: torch.Tensor

    def __init__(
        self,
        level: int = 3,
        axes: Sequence[float] = (1.0, 0.7, 0.7),
        scale: float = 0.6,
        uv_mode: str = "seamless",
        bottom: float = 1.0,
    ) -> None:
        super().__init__()
        if uv_mode not in UV_MODES:
            raise ValueError(f"uv_mode must be one of {UV_MODES}, got {uv_mode!r}")
        # ellipsoid (and icosphere for the level) refuses what builds no template: the values pass through as given,
        # so that int() cannot truncate a level of 2.5 into one
        verts, faces = ellipsoid(level, axes, scale, bottom)
        self.level, self.axes, self.scale, self.uv_mode = (
            int(level),
            tuple(float(a) for a in axes),
            float(scale),
            uv_mode,
        )
        self.bottom = float(bottom)
        vertex_uvs = spherical_vertex_uvs(verts)
        face_uvs = spherical_face_uvs(verts, faces) if uv_mode == "seamless" else vertex_uvs[faces]
        self.register_buffer("verts", verts, persistent=False)
        self.register_buffer("faces", faces, persistent=False)
        self.register_buffer("vertex_uvs", vertex_uvs, persistent=False)
        self.register_buffer("face_uvs", face_uvs, persistent=False)

    @property
    def num_verts(self) -> int:
        return self.verts.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]

    @property
    def wrap_u(self) -> bool:
        """Whether the texture lookup must wrap horizontally (seam-fixed UVs may have u > 1)."""
        return self.uv_mode == "seamless"

    def forward(self, batch_size: int) -> torch.Tensor:
        """The template repeated: (batch_size, V, 3) (a view, do not modify in place)."""
        return self.verts.unsqueeze(0).expand(batch_size, -1, -1)

    def extra_repr(self) -> str:
        return (
            f"level={self.level}, V={self.num_verts}, F={self.num_faces}, axes={self.axes}, "
            f"scale={self.scale}, bottom={self.bottom}, "
            f"uv_mode={self.uv_mode!r}"
        )
