"""unicorn's differentiable mesh renderer, in pure PyTorch (CPU and CUDA).

Pieces, PyTorch3D-style: :func:`rasterize_meshes` turns projected meshes into packed top-K
:class:`Fragments`; textures give every fragment a colour; an aggregator (layered, SoftRas, hard) composites
them into images. The backends put the pieces together and are registered by name::

    from unicorn.render import build_renderer, list_renderers
    renderer = build_renderer("layered", image_size=64, sigma=1e-4)
"""

from .fragments import DenseFragments, Fragments
from .hard import HardBlend, hard_blend
from .layered import LayeredBlend, layered_blend, layered_occupancy
from .raster import blur_radius_from_sigma, rasterize_meshes
from .registry import (
    build_renderer,
    get_renderer_class,
    list_renderers,
    register_renderer,
    unregister_renderer,
)
from .renderer import HardRenderer, LayeredRasterizer, MeshRenderer, RenderOutput, SoftRasRenderer
from .softras import SoftRasBlend, softras_blend
from .textures import Textures, TexturesUV, TexturesVertex, interpolate_vertex_attributes

__all__ = [
    "DenseFragments",
    "Fragments",
    "HardBlend",
    "HardRenderer",
    "LayeredBlend",
    "LayeredRasterizer",
    "MeshRenderer",
    "RenderOutput",
    "SoftRasBlend",
    "SoftRasRenderer",
    "Textures",
    "TexturesUV",
    "TexturesVertex",
    "blur_radius_from_sigma",
    "build_renderer",
    "get_renderer_class",
    "hard_blend",
    "interpolate_vertex_attributes",
    "layered_blend",
    "layered_occupancy",
    "list_renderers",
    "rasterize_meshes",
    "register_renderer",
    "softras_blend",
    "unregister_renderer",
]
