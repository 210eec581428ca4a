"""The built-in backends, registered by name: named compositions of a rasterizer and an aggregator.

Each is a :class:`MeshRenderer` whose constructor takes the backend's options and builds the two parts:

- ``layered`` (:class:`LayeredRasterizer`): soft top-K rasterization + :class:`LayeredBlend`.
- ``softras`` (:class:`SoftRasRenderer`): soft top-K rasterization, nothing truncated + :class:`SoftRasBlend`.
- ``hard`` (:class:`HardRenderer`): supersampled hard rasterization + :class:`HardBlend`.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..geometry.cameras import PerspectiveCamera
from .hard import HardBlend
from .layered import LayeredBlend
from .raster import blur_radius_from_sigma
from .rasterizer import MeshRasterizer
from .registry import register_renderer
from .renderer import MeshRenderer
from .softras import SoftRasBlend, check_temperatures

__all__ = ["HardRenderer", "LayeredRasterizer", "SoftRasRenderer"]


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
        camera, max_candidates, max_bytes, perspective_correct: see :class:`MeshRasterizer`.
        background_color: see :class:`MeshRenderer`.

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

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        sigma: float = 1e-4,
        faces_per_pixel: int = 25,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = (1.0, 1.0, 1.0),
        max_candidates: int = 1 << 23,
        max_bytes: int | None = None,
        perspective_correct: bool = False,
    ) -> None:
        rasterizer = MeshRasterizer(
            image_size, faces_per_pixel, blur_radius_from_sigma(sigma), camera, truncate_opaque=True,
            max_candidates=max_candidates, max_bytes=max_bytes, perspective_correct=perspective_correct,
        )  # fmt: skip
        super().__init__(rasterizer, LayeredBlend(sigma), background_color)


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
        camera, max_candidates, max_bytes, perspective_correct: see :class:`MeshRasterizer`.
        background_color: see :class:`MeshRenderer`.
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
        max_bytes: int | None = None,
        perspective_correct: bool = False,
    ) -> None:
        check_temperatures(sigma, gamma)
        rasterizer = MeshRasterizer(
            image_size, faces_per_pixel, blur_radius_from_sigma(sigma), camera, max_candidates=max_candidates,
            max_bytes=max_bytes, perspective_correct=perspective_correct,
        )  # fmt: skip
        znear = rasterizer.camera.znear if znear is None else znear
        zfar = rasterizer.camera.zfar if zfar is None else zfar
        super().__init__(rasterizer, SoftRasBlend(sigma, gamma, znear, zfar, eps), background_color)


@register_renderer("hard")
class HardRenderer(MeshRenderer):
    """Hard rasterization (nearest face containing the pixel, no blur), optionally supersampled.

    For masks and pictures: with ``supersample = s`` it renders at s times the resolution and averages s x s
    blocks, which anti-aliases edges. Gradients reach colours, textures and the background, not positions.
    ``render(...).fragments`` are at the supersampled resolution.

    Args:
        image_size: H or (H, W) of the output.
        supersample: integer supersampling factor (1 = none).
        camera, max_candidates, max_bytes, perspective_correct: see :class:`MeshRasterizer`.
        background_color: see :class:`MeshRenderer`.
    """

    position_gradients = False

    def __init__(
        self,
        image_size: int | Sequence[int] = 64,
        supersample: int = 2,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = (1.0, 1.0, 1.0),
        max_candidates: int = 1 << 23,
        max_bytes: int | None = None,
        perspective_correct: bool = False,
    ) -> None:
        rasterizer = MeshRasterizer(
            image_size, 1, 0.0, camera, truncate_opaque=True, supersample=supersample, max_candidates=max_candidates,
            max_bytes=max_bytes, perspective_correct=perspective_correct,
        )  # fmt: skip
        super().__init__(rasterizer, HardBlend(supersample), background_color)
