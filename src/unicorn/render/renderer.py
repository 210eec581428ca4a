"""Mesh renderers: camera transform, rasterization into fragments, shading, aggregation.

Every backend takes a batch of meshes with shared topology, verts (B, V, 3) and faces (F, 3), their
:class:`~unicorn.render.textures.Textures`, the world-to-view pose ``x_view = x @ R + T`` and an optional
background image, and returns images (B, C + 1, H, W) whose last channel is alpha.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from ..geometry.cameras import PerspectiveCamera, image_hw, world_to_view
from .compositing import background_pixels
from .fragments import Fragments
from .hard import hard_blend
from .layered import layered_blend
from .raster import blur_radius_from_sigma, check_mesh_inputs, check_pose_inputs, rasterize_meshes
from .registry import register_renderer
from .softras import check_temperatures, softras_blend
from .textures import Textures

__all__ = ["HardRenderer", "LayeredRasterizer", "MeshRenderer", "RenderOutput", "SoftRasRenderer"]


@dataclass
class RenderOutput:
    """Images and the fragments they were made from.

    Attributes:
        images: (B, C + 1, H, W), RGB(...) then alpha.
        fragments: packed fragments at the rasterized resolution.
    """

    images: torch.Tensor
    fragments: Fragments

    @property
    def face_ids(self) -> torch.Tensor:
        """(B, H, W) long, nearest face containing each pixel centre, -1 where none."""
        return self.fragments.first_layer()[0]

    @property
    def depth(self) -> torch.Tensor:
        """(B, 1, H, W) view depth of the nearest face containing each pixel centre, 0 where none."""
        return self.fragments.first_layer()[1].unsqueeze(1)


class MeshRenderer(nn.Module):
    """Base of the backends: everything but the aggregation.

    Args:
        image_size: H or (H, W).
        faces_per_pixel: K, the most faces kept per pixel.
        blur_radius: squared NDC radius within which a face outside the pixel still counts.
        camera: projection; a 30-degree field of view by default (the reference's).
        background_color: colour (C,) behind the mesh when no background image is given.
        max_candidates: rasterizer work budget per chunk of images (bounds memory).
    """

    truncate_opaque = False
    # whether images are differentiable in the vertex positions (the hard backend's are not)
    position_gradients = True

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        faces_per_pixel: int = 1,
        blur_radius: float = 0.0,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = (1.0, 1.0, 1.0),
        max_candidates: int = 1 << 23,
    ) -> None:
        super().__init__()
        self.image_size = image_hw(image_size if isinstance(image_size, int) else tuple(image_size))
        if faces_per_pixel < 1:
            raise ValueError(f"faces_per_pixel must be >= 1, got {faces_per_pixel}")
        self.faces_per_pixel = int(faces_per_pixel)
        if not (math.isfinite(blur_radius) and blur_radius >= 0):
            raise ValueError(f"blur_radius must be finite and >= 0, got {blur_radius}")
        self.blur_radius = float(blur_radius)
        self.camera = camera if camera is not None else PerspectiveCamera(fov=30.0)
        self.register_buffer("background_color", torch.tensor(list(background_color), dtype=torch.float32))
        self.max_candidates = int(max_candidates)

    def extra_repr(self) -> str:
        return (
            f"image_size={self.image_size}, faces_per_pixel={self.faces_per_pixel}, blur_radius={self.blur_radius:.3g}"
        )

    def project(self, verts: torch.Tensor, R: torch.Tensor | None, T: torch.Tensor | None) -> torch.Tensor:
        """World vertices (B, V, 3) to ``(x_ndc, y_ndc, z_view)``; with R and T None, verts are in view space."""
        if (R is None) != (T is None):
            raise ValueError("give both R and T, or neither (verts already in view coordinates)")
        view = verts if R is None else world_to_view(verts, R, T)
        return self.camera.project(view)

    def rasterize(
        self,
        verts: torch.Tensor,
        faces: torch.Tensor,
        R: torch.Tensor | None = None,
        T: torch.Tensor | None = None,
        image_size: tuple[int, int] | None = None,
    ) -> Fragments:
        """Fragments of the meshes (B, V, 3) / (F, 3) seen with pose (R, T)."""
        check_mesh_inputs(verts, faces)
        check_pose_inputs(R, T, verts.shape[0])
        return self._rasterize(verts, faces, R, T, image_size)

    def _rasterize(
        self,
        verts: torch.Tensor,
        faces: torch.Tensor,
        R: torch.Tensor | None,
        T: torch.Tensor | None,
        image_size: tuple[int, int] | None,
    ) -> Fragments:
        # inputs already checked by the caller (each check is a host sync on CUDA: once per render)
        return rasterize_meshes(
            self.project(verts, R, T), faces, image_size or self.image_size, self.blur_radius,
            self.faces_per_pixel, self.truncate_opaque, self.max_candidates, check_inputs=False,
        )  # fmt: skip

    @property
    def raster_size(self) -> tuple[int, int]:
        """(H, W) at which fragments are computed; the output size unless a backend supersamples."""
        return self.image_size

    def blend(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        """Images (B, C + 1, H, W) from fragment colours (M, C) and the background table (B * H * W, C)."""
        raise NotImplementedError

    def _check_inputs(self, textures: Textures, verts: torch.Tensor, faces: torch.Tensor) -> None:
        check_mesh_inputs(verts, faces)
        if not isinstance(textures, Textures):
            raise TypeError(f"textures must be TexturesUV or TexturesVertex, got {type(textures).__name__}")
        textures.check_batch(verts.shape[0], num_verts=verts.shape[1], num_faces=faces.shape[0])

    def render(
        self,
        verts: torch.Tensor,
        faces: torch.Tensor,
        textures: Textures,
        R: torch.Tensor | None = None,
        T: torch.Tensor | None = None,
        background: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Render and keep the fragments (for depth and face ids). Arguments as :meth:`forward`."""
        self._check_inputs(textures, verts, faces)
        check_pose_inputs(R, T, verts.shape[0])
        fragments = self._rasterize(verts, faces, R, T, self.raster_size)
        colors = textures.sample(fragments, faces.long())
        bg = background_pixels(
            background, self.background_color, verts.shape[0], self.image_size, textures.num_channels, colors
        )
        return RenderOutput(self.blend(colors, fragments, bg), fragments)

    def forward(
        self,
        verts: torch.Tensor,
        faces: torch.Tensor,
        textures: Textures,
        R: torch.Tensor | None = None,
        T: torch.Tensor | None = None,
        background: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Render a batch of textured meshes.

        Args:
            verts: (B, V, 3) vertices in world coordinates (view coordinates if R and T are None).
            faces: (F, 3) long, shared by the batch.
            textures: :class:`TexturesUV` or :class:`TexturesVertex` with batch size B and C channels.
            R: (B, 3, 3) world-to-view rotation, ``x_view = x @ R + T``.
            T: (B, 3) world-to-view translation.
            background: (B, C, H, W) background images; ``background_color`` when None.

        Returns:
            (B, C + 1, H, W) images, the last channel alpha.
        """
        return self.render(verts, faces, textures, R, T, background).images


@register_renderer("layered")
class LayeredRasterizer(MeshRenderer):
    """UNICORN's renderer: soft top-K rasterization and layered alpha compositing.

    Occupancy ``exp(min(0, -d) / sigma)`` on squared NDC distances: 1 inside a face, fading over about a pixel
    outside; faces are composited front to back. The blur radius follows from ``sigma`` (occupancy 1e-4 at the
    edge), and faces behind the first opaque one are dropped exactly.

    Args:
        image_size: H or (H, W).
        sigma: occupancy temperature (1e-4 in the reference); 0 renders hard edges.
        faces_per_pixel: K (25 for real images, 50 for ShapeNet in the reference).
        camera, background_color, max_candidates: see :class:`MeshRenderer`.

    Example:
        >>> import torch
        >>> from unicorn.geometry.mesh import icosphere
        >>> from unicorn.geometry.rotations import look_at_view_transform
        >>> from unicorn.render import LayeredRasterizer, TexturesVertex
        >>> verts, faces = icosphere(2)
        >>> R, T = look_at_view_transform(dist=2.7, elev=30.0, azim=45.0)
        >>> renderer = LayeredRasterizer(image_size=32)
        >>> images = renderer(verts[None] * 0.5, faces, TexturesVertex(torch.rand(1, len(verts), 3)), R=R, T=T)
        >>> tuple(images.shape)
        (1, 4, 32, 32)
    """

    truncate_opaque = True

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        sigma: float = 1e-4,
        faces_per_pixel: int = 25,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = (1.0, 1.0, 1.0),
        max_candidates: int = 1 << 23,
    ) -> None:
        super().__init__(
            image_size,
            faces_per_pixel,
            blur_radius_from_sigma(sigma),
            camera,
            background_color,
            max_candidates,
        )
        self.sigma = float(sigma)

    def blend(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return layered_blend(colors, fragments, bg_table, self.sigma)


@register_renderer("softras")
class SoftRasRenderer(MeshRenderer):
    """SoftRasterizer-style aggregation (sigmoid occupancy, depth softmax with a background layer).

    Args:
        image_size: H or (H, W).
        sigma: occupancy temperature on squared NDC distances.
        gamma: depth softmax temperature.
        faces_per_pixel: K; unlike the layered renderer nothing is exactly hidden, so K must cover the depth
            complexity within the blur radius.
        eps: normalised inverse depth of the background layer.
        znear, zfar: depth normalisation; the camera's when None.
        camera, background_color, max_candidates: see :class:`MeshRenderer`.
    """

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        sigma: float = 1e-4,
        gamma: float = 1e-4,
        faces_per_pixel: int = 50,
        eps: float = 1e-3,
        znear: float | None = None,
        zfar: float | None = None,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = (1.0, 1.0, 1.0),
        max_candidates: int = 1 << 23,
    ) -> None:
        check_temperatures(sigma, gamma)
        super().__init__(
            image_size,
            faces_per_pixel,
            blur_radius_from_sigma(sigma),
            camera,
            background_color,
            max_candidates,
        )
        self.sigma, self.gamma, self.eps = float(sigma), float(gamma), float(eps)
        self.znear = self.camera.znear if znear is None else float(znear)
        self.zfar = self.camera.zfar if zfar is None else float(zfar)

    def blend(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return softras_blend(colors, fragments, bg_table, self.sigma, self.gamma, self.znear, self.zfar, self.eps)


@register_renderer("hard")
class HardRenderer(MeshRenderer):
    """Hard rasterization (nearest face containing the pixel, no blur), optionally supersampled.

    For masks and pictures: with ``supersample = s`` it renders at s times the resolution and averages s x s
    blocks, which anti-aliases edges. Gradients reach colours, textures and the background, not positions.
    ``render(...).fragments`` are at the supersampled resolution.

    Args:
        image_size: H or (H, W) of the output.
        supersample: integer supersampling factor (1 = none).
        camera, background_color, max_candidates: see :class:`MeshRenderer`.
    """

    truncate_opaque = True
    position_gradients = False

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        supersample: int = 2,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = (1.0, 1.0, 1.0),
        max_candidates: int = 1 << 23,
    ) -> None:
        super().__init__(image_size, 1, 0.0, camera, background_color, max_candidates)
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.supersample = int(supersample)

    @property
    def raster_size(self) -> tuple[int, int]:
        H, W = self.image_size
        return H * self.supersample, W * self.supersample

    def blend(self, colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor) -> torch.Tensor:
        return hard_blend(colors, fragments, bg_table, self.supersample)
