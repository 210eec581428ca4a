"""Surface colours sampled at the rasterized fragments: per-vertex colours or a UV texture image."""

from __future__ import annotations

import torch

from ..checks import check_faces, check_same_dtype, check_shape
from .fragments import Fragments
from .precision import to_full_precision

__all__ = ["Textures", "TexturesUV", "TexturesVertex", "interpolate_vertex_attributes"]


def interpolate_vertex_attributes(fragments: Fragments, faces: torch.Tensor, attrs: torch.Tensor) -> torch.Tensor:
    """Barycentric interpolation of per-vertex attributes at every fragment.

    Args:
        fragments: packed fragments with M pairs.
        faces: (F, 3) the faces that were rasterized.
        attrs: (B, V, D) per-vertex attributes, or (V, D) shared by the batch.

    Returns:
        (M, D) interpolated attributes.

    Raises:
        ValueError, TypeError: ``attrs`` not floating point or of another batch, ``faces`` not integer (F, 3) or
            indexing past ``attrs``' vertices (the range read outside :func:`unicorn.hostsync.sync_free`).
    """
    check_shape(attrs, "B, V, D | V, D", "attrs", {"B": fragments.batch_size}, floating=True)
    check_faces(faces, attrs.shape[-2], allow_empty=True)
    return _interpolate(fragments, faces, attrs)


def _interpolate(fragments: Fragments, faces: torch.Tensor, attrs: torch.Tensor) -> torch.Tensor:
    """:func:`interpolate_vertex_attributes` of checked arguments (a renderer checks the mesh and textures once)."""
    if attrs.dim() == 2:
        vert_idx = faces.index_select(0, fragments.face).long()  # (M, 3); index_select takes int32 or int64 only
        values = attrs.index_select(0, vert_idx.reshape(-1)).view(*vert_idx.shape, attrs.shape[-1])
    else:
        V = attrs.shape[1]
        vert_idx = fragments.batch_index.unsqueeze(1) * V + faces.index_select(0, fragments.face)
        values = (
            attrs.reshape(-1, attrs.shape[-1])
            .index_select(0, vert_idx.reshape(-1))
            .view(*vert_idx.shape, attrs.shape[-1])
        )
    return (fragments.bary.unsqueeze(-1).to(values.dtype) * values).sum(1)


class Textures:
    """Something that gives a colour (M, C) to every fragment."""

    num_channels: int

    def sample(self, fragments: Fragments, faces: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def check_batch(
        self,
        batch_size: int,
        num_verts: int | None = None,
        num_faces: int | None = None,
        verts: torch.Tensor | None = None,
    ) -> None:  # pragma: no cover - interface
        """Raise ValueError unless the textures fit ``batch_size`` meshes of ``num_verts`` / ``num_faces``, and
        TypeError unless their colours have the dtype of ``verts`` when given."""
        raise NotImplementedError

    def tensors(self) -> dict[str, torch.Tensor]:
        """The tensors whose values reach the pixels, by argument name: the renderer requires them finite (in the
        host read it makes anyway). None by default."""
        return {}

    def full_precision(self) -> Textures:
        """These textures with float16 and bfloat16 tensors in float32 (the renderer's inputs under autocast);
        ``self`` by default."""
        return self


class TexturesVertex(Textures):
    """Per-vertex colours, interpolated with the barycentrics.

    Args:
        colors: (B, V, C) colours, typically in [0, 1].
    """

    def __init__(self, colors: torch.Tensor) -> None:
        check_shape(colors, "B, V, C", "colors")
        if not colors.dtype.is_floating_point:
            raise TypeError(f"colors must be a float tensor, got {colors.dtype}")
        self.colors = colors
        self.num_channels = colors.shape[-1]

    def check_batch(
        self,
        batch_size: int,
        num_verts: int | None = None,
        num_faces: int | None = None,
        verts: torch.Tensor | None = None,
    ) -> None:
        if self.colors.shape[0] != batch_size:
            raise ValueError(f"colors have batch size {self.colors.shape[0]}, meshes {batch_size}")
        if num_verts is not None and self.colors.shape[1] != num_verts:
            raise ValueError(f"colors have {self.colors.shape[1]} vertices, meshes {num_verts}")
        if verts is not None:
            check_same_dtype(verts, self.colors, "verts", "colors")

    def tensors(self) -> dict[str, torch.Tensor]:
        return {"colors": self.colors}

    def full_precision(self) -> TexturesVertex:
        return TexturesVertex(to_full_precision(self.colors))

    def sample(self, fragments: Fragments, faces: torch.Tensor) -> torch.Tensor:
        return _interpolate(fragments, faces, self.colors)  # the renderer checked faces and colours


class TexturesUV(Textures):
    """A texture image per mesh, addressed by per-face-vertex UV coordinates and sampled bilinearly.

    ``u`` runs left to right and ``v`` bottom to top (``v = 0`` is the image's last row), as in PyTorch3D and
    the UNICORN reference.

    Args:
        maps: (B, C, Ht, Wt) texture images, or PyTorch3D's (B, Ht, Wt, C) with C <= 4 channels (recognised by
            a last dimension of at most 4 under a larger second one, or forced with ``channels_last``); kept
            as (B, C, Ht, Wt) in ``self.maps``. A shape that reads both ways (second and last dimensions both
            at most 4) needs ``channels_last``.
        face_uvs: (F, 3, 2) UV coordinates of the three corners of every face, shared by the batch.
        wrap_u: sample periodically in ``u`` (period 1), so that a face straddling the seam of a spherical
            parametrisation (corners with ``u`` slightly above 1) reads the texture across the seam instead
            of across the whole image. Uses ``align_corners=False`` horizontally, the only choice for which the
            period is exactly one texture width.
        align_corners: texel centres at the image borders (``x = u * (Wt - 1)``, as ``grid_sample`` with
            ``align_corners=True``) instead of half a texel inside. Must be False with ``wrap_u``. The
            released UNICORN models used ``align_corners=True, wrap_u=False``.
        channels_last: the layout of ``maps``: True for PyTorch3D's (B, Ht, Wt, C), False for (B, C, Ht, Wt),
            None to recognise it from the shape.
    """

    def __init__(
        self,
        maps: torch.Tensor,
        face_uvs: torch.Tensor,
        wrap_u: bool = True,
        align_corners: bool = False,
        channels_last: bool | None = None,
    ) -> None:
        check_shape(maps, "B, C, Ht, Wt | B, Ht, Wt, C", "maps")  # ours, or PyTorch3D's
        if channels_last is None:
            if maps.shape[1] <= 4 and maps.shape[-1] <= 4:  # (1, 4, 4, 3): 4 channels of 4 x 3, or 3 of 4 x 4
                raise ValueError(
                    f"maps {tuple(maps.shape)} reads as (B, C, Ht, Wt) and as PyTorch3D's (B, Ht, Wt, C): say which "
                    "with channels_last=False or True"
                )
            channels_last = maps.shape[-1] <= 4 < maps.shape[1]
        if channels_last:
            maps = maps.permute(0, 3, 1, 2)
        if not maps.dtype.is_floating_point:
            raise TypeError(f"maps must be a float tensor, got {maps.dtype}")
        if 0 in maps.shape[1:]:
            raise ValueError(f"maps needs at least one channel and one texel, got (B, C, Ht, Wt) = {tuple(maps.shape)}")
        check_shape(face_uvs, "F, 3, 2", "face_uvs", floating=True)
        if wrap_u and align_corners:
            raise ValueError("wrap_u=True needs align_corners=False (the period must be one texture width)")
        self.maps = maps
        self.face_uvs = face_uvs
        self.wrap_u = wrap_u
        self.align_corners = align_corners
        self.num_channels = maps.shape[1]

    def check_batch(
        self,
        batch_size: int,
        num_verts: int | None = None,
        num_faces: int | None = None,
        verts: torch.Tensor | None = None,
    ) -> None:
        if self.maps.shape[0] != batch_size:
            raise ValueError(f"texture maps have batch size {self.maps.shape[0]}, meshes {batch_size}")
        if num_faces is not None and self.face_uvs.shape[0] != num_faces:
            raise ValueError(f"face_uvs has {self.face_uvs.shape[0]} faces, meshes {num_faces}")
        if verts is not None:
            check_same_dtype(verts, self.maps, "verts", "maps")  # face_uvs follow the vertices' dtype

    def tensors(self) -> dict[str, torch.Tensor]:
        return {"maps": self.maps, "face_uvs": self.face_uvs}

    def full_precision(self) -> TexturesUV:
        maps, face_uvs = to_full_precision(self.maps), to_full_precision(self.face_uvs)
        return TexturesUV(maps, face_uvs, self.wrap_u, self.align_corners, channels_last=False)

    def sample(self, fragments: Fragments, faces: torch.Tensor) -> torch.Tensor:
        corner_uvs = self.face_uvs.to(fragments.bary).reshape(-1, 6).index_select(0, fragments.face).view(-1, 3, 2)
        uv = (fragments.bary.unsqueeze(-1) * corner_uvs).sum(1)
        return sample_bilinear(self.maps, fragments.batch_index, uv, self.wrap_u, self.align_corners)


def sample_bilinear(
    maps: torch.Tensor, batch_index: torch.Tensor, uv: torch.Tensor, wrap_u: bool, align_corners: bool
) -> torch.Tensor:
    """Bilinear lookup of ``maps`` (B, C, Ht, Wt) at points ``uv`` (M, 2) of images ``batch_index`` (M,).

    Returns (M, C). Rows are clamped to the border; columns wrap when ``wrap_u`` else clamp.
    """
    B, C, Ht, Wt = maps.shape
    u, v = uv[:, 0], 1.0 - uv[:, 1]
    if align_corners:
        x, y = u * (Wt - 1), v * (Ht - 1)
    else:
        x, y = u * Wt - 0.5, v * Ht - 0.5
    x0f, y0f = torch.floor(x.detach()), torch.floor(y.detach())
    fx, fy = (x - x0f).unsqueeze(1), (y - y0f).unsqueeze(1)
    x0, y0 = x0f.long(), y0f.long()
    if wrap_u:
        xs = (x0 % Wt, (x0 + 1) % Wt)
    else:
        xs = (x0.clamp(0, Wt - 1), (x0 + 1).clamp(0, Wt - 1))
    ys = (y0.clamp(0, Ht - 1), (y0 + 1).clamp(0, Ht - 1))
    table = maps.permute(0, 2, 3, 1).reshape(-1, C)
    base = batch_index * (Ht * Wt)

    def tap(yi: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
        return table.index_select(0, base + yi * Wt + xi)

    top = tap(ys[0], xs[0]) * (1 - fx) + tap(ys[0], xs[1]) * fx
    bottom = tap(ys[1], xs[0]) * (1 - fx) + tap(ys[1], xs[1]) * fx
    return top * (1 - fy) + bottom * fy
