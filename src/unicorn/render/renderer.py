"""The renderer: a rasterizer and an aggregator composed (PyTorch3D's ``MeshRenderer(rasterizer, shader)``).

A renderer takes a batch of meshes with shared topology, verts (B, V, 3) and faces (F, 3), their
:class:`~unicorn.render.textures.Textures`, the world-to-view pose ``x_view = x @ R + T`` and an optional
background image, and returns images (B, C + 1, H, W) whose last channel is alpha. The rasterizer
(:class:`~unicorn.render.rasterizer.MeshRasterizer`) makes the fragments, the textures colour them and the
aggregator (:class:`~unicorn.render.layered.LayeredBlend`, :class:`~unicorn.render.softras.SoftRasBlend`,
:class:`~unicorn.render.hard.HardBlend` or any module with that call signature) composites them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from ..checks import check_same_dtype
from ..geometry.cameras import PerspectiveCamera
from .compositing import background_pixels
from .fragments import Fragments
from .precision import float32_boundary
from .raster import RenderError, check_mesh_inputs, check_pose_inputs
from .rasterizer import MeshRasterizer
from .settings import BACKGROUND_COLOR, check_render_option
from .textures import Textures

__all__ = ["MeshRenderer", "RenderOutput"]


@dataclass
class RenderOutput:
    """Images and the fragments they were made from.

    Attributes:
        images: (B, C + 1, H, W), RGB(...) then alpha.
        fragments: packed fragments at the rasterized resolution: (sH, sW) for a rasterizer that supersamples
            ``s`` times (:class:`~unicorn.render.rasterizer.MeshRasterizer`'s ``supersample``), (H, W) otherwise.
    """

    images: torch.Tensor
    fragments: Fragments

    @property
    def face_ids(self) -> torch.Tensor:
        """(B, sH, sW) long, at the rasterized resolution (``s`` = 1 without supersampling): the nearest face
        covering each sample, -1 where none."""
        return self.fragments.first_layer()[0]

    @property
    def depth(self) -> torch.Tensor:
        """(B, 1, sH, sW), at the rasterized resolution: the view depth of the nearest face covering each sample,
        0 where none; differentiable (a depth loss reaches the vertices, as through PyTorch3D's ``zbuf``)."""
        return self.fragments.first_layer()[1].unsqueeze(1)


def _check_supersampling(rasterizer: nn.Module, blend: nn.Module) -> None:
    """Refuse an aggregator whose ``supersample`` (the supersampling it averages; the built-in ones declare it) is
    not the rasterizer's: it would fail at the first render on a background of another size than the fragments',
    in an error naming neither."""
    averages = getattr(blend, "supersample", None)
    if averages is None:  # an aggregator that does not say: its own business
        return
    supersample = getattr(rasterizer, "supersample", 1)
    if supersample != averages:
        raise RenderError(
            f"the rasterizer supersamples {supersample} times but the blend {type(blend).__name__} averages "
            f"supersample={averages}: give HardBlend(supersample={supersample}) (LayeredBlend and SoftRasBlend take "
            "fragments at the image size, supersample=1)"
        )


class MeshRenderer(nn.Module):
    """Rasterize, colour the fragments from the textures, aggregate them over the background.

    Args:
        rasterizer: makes the fragments at its ``raster_size``; its ``image_size`` is the output size.
        blend: the aggregator, called as ``blend(colors (M, C), fragments, bg_table (B * H * W, C))`` and
            returning images (B, C + 1, H, W). One that declares ``supersample`` (the built-in ones) must take the
            rasterizer's (``HardBlend(s)`` for ``supersample = s``; LayeredBlend and SoftRasBlend 1), else
            RenderError.
        background_color: colour (C,) behind the mesh when no background image is given.
    """

    # whether the silhouettes follow the vertex positions under gradient descent (the hard backend's do not: its
    # gradients reach the positions only through the colours interpolated inside each face)
    position_gradients = True

    def __init__(
        self,
        rasterizer: MeshRasterizer,
        blend: nn.Module,
        background_color: Sequence[float] = BACKGROUND_COLOR,
    ) -> None:
        super().__init__()
        for name, part in (("rasterizer", rasterizer), ("blend", blend)):
            if not isinstance(part, nn.Module):  # a module of its own, moved and saved with the renderer
                raise TypeError(f"{name} must be an nn.Module (a {name} of unicorn.render), got {type(part).__name__}")
        check_render_option("background_color", background_color)
        _check_supersampling(rasterizer, blend)
        self.rasterizer = rasterizer
        self.blend = blend
        self.register_buffer("background_color", torch.tensor(list(background_color), dtype=torch.float32))

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) of the output images."""
        return self.rasterizer.image_size

    @property
    def raster_size(self) -> tuple[int, int]:
        """(H, W) at which fragments are computed; the output size unless the rasterizer supersamples."""
        return self.rasterizer.raster_size

    @property
    def camera(self) -> PerspectiveCamera:
        """The rasterizer's camera."""
        return self.rasterizer.camera

    def rasterize(
        self, verts: torch.Tensor, faces: torch.Tensor, R: torch.Tensor | None = None, T: torch.Tensor | None = None
    ) -> Fragments:
        """Fragments of the meshes (B, V, 3) / (F, 3) seen with pose (R, T), at the output size (not supersampled);
        ``self.rasterizer(...)`` for others."""
        return self.rasterizer(verts, faces, R, T, self.image_size)

    @float32_boundary
    def render(
        self,
        verts: torch.Tensor,
        faces: torch.Tensor,
        textures: Textures,
        R: torch.Tensor | None = None,
        T: torch.Tensor | None = None,
        background: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Render and keep the fragments (for depth and face ids). Arguments as :meth:`forward`; under autocast
        the depth tests and the compositing run in float32 (:func:`~unicorn.render.precision.float32_boundary`)."""
        if not isinstance(textures, Textures):
            raise TypeError(f"textures must be TexturesUV or TexturesVertex, got {type(textures).__name__}")
        # the textures' and background's finiteness is read with the mesh's (one host read): NaN colours would give
        # NaN pixels
        colours = dict(textures.tensors())
        if background is not None:
            if not torch.is_tensor(background) or not background.dtype.is_floating_point:
                kind = background.dtype if torch.is_tensor(background) else type(background).__name__
                raise TypeError(f"background must be a floating-point tensor (B, C, H, W) in [0, 1], got {kind}")
            colours["background"] = background
        check_mesh_inputs(verts, faces, finite_also=colours)
        if background is not None:  # as the textures: no silent cast (a float64 background lost its precision)
            check_same_dtype(verts, background, "verts", "background")
        textures.check_batch(verts.shape[0], num_verts=verts.shape[1], num_faces=faces.shape[0], verts=verts)
        check_pose_inputs(R, T, verts.shape[0])
        fragments = self.rasterizer(verts, faces, R, T, check_inputs=False)  # checked once above
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
            verts: (B, V, 3) float32 or float64 vertices in world coordinates (view coordinates if R and T are
                None), finite.
            faces: (F, 3) long, shared by the batch.
            textures: :class:`TexturesUV` or :class:`TexturesVertex` with batch size B and C channels, finite, of
                the vertices' dtype (no silent promotion: a mismatch is a TypeError naming both). Under
                ``torch.autocast`` every float16 or bfloat16 input (vertices, textures, pose, background) is cast to
                float32 first and the render runs with autocast off (:mod:`unicorn.render.precision`).
            R: (B, 3, 3) floating point world-to-view rotation, ``x_view = x @ R + T``, finite; of any floating
                dtype, applied in the vertices' (a float32 pose with float64 vertices renders in float64).
            T: (B, 3) floating point world-to-view translation, finite; likewise.
            background: (B, C, H, W) background images of the vertices' dtype, finite, on their device;
                ``background_color`` when None.

        Returns:
            (B, C + 1, H, W) images, the last channel alpha, of the (cast) vertices' dtype: float32 at least under
            autocast.

        Raises:
            TypeError, ValueError: a bad argument, named in the one-line message; ValueError also when the
                fragments could exceed the renderer's memory limit (:func:`~unicorn.render.raster.check_render_size`).
        """
        return self.render(verts, faces, textures, R, T, background).images
