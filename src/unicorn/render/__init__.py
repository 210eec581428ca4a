"""unicorn's differentiable mesh renderer, in pure PyTorch (CPU and CUDA).

Pieces, PyTorch3D-style: a :class:`MeshRasterizer` turns projected meshes into packed top-K :class:`Fragments`
(:func:`rasterize_meshes`); textures give every fragment a colour; an aggregator (:class:`LayeredBlend`,
:class:`SoftRasBlend`, :class:`HardBlend`, each with its function) composites them into images. A
:class:`MeshRenderer` composes a rasterizer and an aggregator; the built-in compositions are registered by
name, and take their options (defaults and ranges: :class:`RenderSettings`) as keywords::

    from unicorn.render import build_renderer, list_renderers
    renderer = build_renderer("layered", image_size=64, sigma=1e-4)
"""

from .backends import HardRenderer, LayeredRasterizer, LayeredRenderer, SoftRasRenderer
from .fragments import DenseFragments, Fragments, check_blend_inputs
from .hard import HardBlend, hard_blend
from .layered import LayeredBlend, layered_blend, layered_occupancy
from .overflow import OverflowCounter, RenderOverflowWarning
from .raster import (
    DEFAULT_MAX_RENDER_BYTES,
    MAX_RENDER_BYTES_ENV,
    RenderError,
    RenderSizeError,
    blur_radius_from_sigma,
    check_render_size,
    max_render_bytes,
    rasterize_meshes,
)
from .rasterizer import MeshRasterizer
from .registry import (
    RENDERERS,
    build_renderer,
    get_renderer_class,
    list_renderers,
    register_renderer,
    unregister_renderer,
)
from .renderer import MeshRenderer, RenderOutput
from .settings import BACKGROUND_COLOR, DEFAULT_SETTINGS, RenderSettings, check_render_option
from .softras import SoftRasBlend, softras_blend
from .textures import Textures, TexturesUV, TexturesVertex, interpolate_vertex_attributes

__all__ = [
    "BACKGROUND_COLOR",
    "DEFAULT_SETTINGS",
    "DEFAULT_MAX_RENDER_BYTES",
    "MAX_RENDER_BYTES_ENV",
    "DenseFragments",
    "Fragments",
    "HardBlend",
    "HardRenderer",
    "LayeredBlend",
    "LayeredRasterizer",
    "LayeredRenderer",
    "MeshRasterizer",
    "MeshRenderer",
    "OverflowCounter",
    "RENDERERS",
    "RenderError",
    "RenderOutput",
    "RenderOverflowWarning",
    "RenderSettings",
    "RenderSizeError",
    "SoftRasBlend",
    "SoftRasRenderer",
    "Textures",
    "TexturesUV",
    "TexturesVertex",
    "blur_radius_from_sigma",
    "build_renderer",
    "check_blend_inputs",
    "check_render_option",
    "check_render_size",
    "get_renderer_class",
    "hard_blend",
    "interpolate_vertex_attributes",
    "layered_blend",
    "layered_occupancy",
    "list_renderers",
    "max_render_bytes",
    "rasterize_meshes",
    "register_renderer",
    "softras_blend",
    "unregister_renderer",
]
