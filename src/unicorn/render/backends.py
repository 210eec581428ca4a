"""The built-in backends, registered by name: named compositions of a rasterizer and an aggregator.

Each is a :class:`MeshRenderer` whose constructor takes the backend's options, checks them as one
:class:`~unicorn.render.settings.RenderSettings` (read back as ``renderer.settings``; defaults and ranges are
defined there) and builds the two parts:

- ``layered`` (:class:`LayeredRenderer`, also importable as ``LayeredRasterizer``): soft top-K rasterization +
  :class:`LayeredBlend`.
- ``softras`` (:class:`SoftRasRenderer`): soft top-K rasterization, nothing truncated + :class:`SoftRasBlend`.
- ``hard`` (:class:`HardRenderer`): supersampled hard rasterization + :class:`HardBlend`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from torch import nn

from ..geometry.cameras import PerspectiveCamera
from .hard import HardBlend
from .layered import LayeredBlend
from .raster import blur_radius_from_sigma
from .rasterizer import MeshRasterizer
from .registry import register_renderer
from .renderer import MeshRenderer
from .settings import DEFAULT_SETTINGS as D
from .settings import RenderSettings, buffer_color
from .softras import SoftRasBlend, check_temperatures

__all__ = ["HardRenderer", "LayeredRasterizer", "LayeredRenderer", "SoftRasRenderer"]


class _Backend(MeshRenderer):
    """A built-in backend: a :class:`MeshRenderer` that keeps the options it was built with."""

    def __init__(self, rasterizer: MeshRasterizer, blend: nn.Module, settings: RenderSettings) -> None:
        super().__init__(rasterizer, blend, settings.background_color)
        self._settings = settings

    @property
    def settings(self) -> RenderSettings:
        """The options the renderer renders with. The background colour is the ``background_color`` buffer's
        (:func:`~unicorn.render.settings.buffer_color`, one host read), which a loaded state dict, an in-place edit or
        a 16-bit conversion may have changed since the renderer was built."""
        color = buffer_color(self.background_color, self._settings.background_color)
        return dataclasses.replace(self._settings, background_color=color)


@register_renderer("layered")
class LayeredRenderer(_Backend):
    """UNICORN's renderer: soft top-K rasterization and layered alpha compositing.

    Occupancy ``exp(min(0, -d) / sigma)`` on squared NDC distances: 1 inside a face, fading over about a pixel
    outside; faces are composited front to back. The blur radius follows from ``sigma`` (occupancy 1e-4 at the
    edge), and faces behind the first opaque one are dropped exactly.

    Args:
        image_size, sigma, faces_per_pixel, background_color, max_candidates, max_bytes, perspective_correct: see
            :class:`~unicorn.render.settings.RenderSettings` (sigma 0 renders hard edges).
        camera: see :class:`MeshRasterizer`.

    Example:
        >>> import torch
        >>> from unicorn.geometry.mesh import icosphere
        >>> from unicorn.geometry.rotations import look_at_view_transform
        >>> from unicorn.render import LayeredRenderer, TexturesVertex
        >>> verts, faces = icosphere(2)
        >>> R, T = look_at_view_transform(dist=2.7, elev=30.0, azim=45.0)
        >>> renderer = LayeredRenderer(image_size=32)
        >>> images = renderer(verts[None] * 0.5, faces, TexturesVertex(torch.rand(1, len(verts), 3)), R=R, T=T)
        >>> tuple(images.shape)
        (1, 4, 32, 32)
    """

    def __init__(
        self,
        image_size: int | Sequence[int] = D.image_size,
        sigma: float = D.sigma,
        faces_per_pixel: int = D.faces_per_pixel,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = D.background_color,
        max_candidates: int = D.max_candidates,
        max_bytes: int | None = D.max_bytes,
        perspective_correct: bool = D.perspective_correct,
    ) -> None:
        s = RenderSettings(
            image_size=image_size, sigma=sigma, faces_per_pixel=faces_per_pixel, background_color=background_color,
            max_candidates=max_candidates, max_bytes=max_bytes, perspective_correct=perspective_correct,
        )  # fmt: skip
        rasterizer = MeshRasterizer(
            s.image_size, s.faces_per_pixel, blur_radius_from_sigma(s.sigma), camera, truncate_opaque=True,
            max_candidates=s.max_candidates, max_bytes=s.max_bytes, perspective_correct=s.perspective_correct,
        )  # fmt: skip
        super().__init__(rasterizer, LayeredBlend(s.sigma), s)


#: the layered renderer's earlier name (it is a whole renderer, not a rasterizer), kept for the users who import it
LayeredRasterizer = LayeredRenderer


@register_renderer("softras")
class SoftRasRenderer(_Backend):
    """SoftRasterizer-style aggregation (sigmoid occupancy, depth softmax with a background layer).

    Args:
        image_size, sigma, gamma, eps, background_color, max_candidates, max_bytes, perspective_correct: see
            :class:`~unicorn.render.settings.RenderSettings` (sigma and gamma > 0).
        faces_per_pixel: K (50 here); unlike the layered renderer nothing is exactly hidden, so K must cover the
            depth complexity within the blur radius.
        znear, zfar: depth normalisation; the camera's when None.
        camera: see :class:`MeshRasterizer`.
    """

    def __init__(
        self,
        image_size: int | Sequence[int] = D.image_size,
        sigma: float = D.sigma,
        gamma: float = D.gamma,
        faces_per_pixel: int = 50,
        eps: float = D.eps,
        znear: float | None = None,
        zfar: float | None = None,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = D.background_color,
        max_candidates: int = D.max_candidates,
        max_bytes: int | None = D.max_bytes,
        perspective_correct: bool = D.perspective_correct,
    ) -> None:
        s = RenderSettings(
            image_size=image_size, sigma=sigma, gamma=gamma, faces_per_pixel=faces_per_pixel, eps=eps,
            background_color=background_color, max_candidates=max_candidates, max_bytes=max_bytes,
            perspective_correct=perspective_correct,
        )  # fmt: skip
        check_temperatures(s.sigma, s.gamma)
        rasterizer = MeshRasterizer(
            s.image_size, s.faces_per_pixel, blur_radius_from_sigma(s.sigma), camera,
            max_candidates=s.max_candidates, max_bytes=s.max_bytes, perspective_correct=s.perspective_correct,
        )  # fmt: skip
        znear = rasterizer.camera.znear if znear is None else znear
        zfar = rasterizer.camera.zfar if zfar is None else zfar
        super().__init__(rasterizer, SoftRasBlend(s.sigma, s.gamma, znear, zfar, s.eps), s)


@register_renderer("hard")
class HardRenderer(_Backend):
    """Hard rasterization (nearest face containing the pixel, no blur), optionally supersampled.

    For masks and pictures: with ``supersample = s`` it renders at s times the resolution and averages s x s
    blocks, which anti-aliases edges. Gradients reach colours, textures and the background; the positions only
    through the colours interpolated inside each face, so silhouettes do not follow the vertices.
    ``render(...).fragments`` are at the supersampled resolution.

    Args:
        image_size, supersample, background_color, max_candidates, max_bytes, perspective_correct: see
            :class:`~unicorn.render.settings.RenderSettings` (``image_size`` is the output's).
        camera: see :class:`MeshRasterizer`.
    """

    position_gradients = False

    def __init__(
        self,
        image_size: int | Sequence[int] = D.image_size,
        supersample: int = D.supersample,
        camera: PerspectiveCamera | None = None,
        background_color: Sequence[float] = D.background_color,
        max_candidates: int = D.max_candidates,
        max_bytes: int | None = D.max_bytes,
        perspective_correct: bool = D.perspective_correct,
    ) -> None:
        s = RenderSettings(
            image_size=image_size, supersample=supersample, background_color=background_color,
            max_candidates=max_candidates, max_bytes=max_bytes, perspective_correct=perspective_correct,
        )  # fmt: skip
        rasterizer = MeshRasterizer(
            s.image_size, 1, 0.0, camera, truncate_opaque=True, supersample=s.supersample,
            max_candidates=s.max_candidates, max_bytes=s.max_bytes, perspective_correct=s.perspective_correct,
        )  # fmt: skip
        super().__init__(rasterizer, HardBlend(s.supersample), s)
