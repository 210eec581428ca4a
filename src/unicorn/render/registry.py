"""The renderer backends by name: one :class:`~unicorn.registry.Registry` (:data:`RENDERERS`).

Backends are ``nn.Module`` classes whose constructor takes keyword options and whose ``forward`` follows
:class:`unicorn.render.MeshRenderer`; the built-in ones (:mod:`unicorn.render.backends`) are named compositions of
a rasterizer and an aggregator. Another package registers its own with the decorator::

    @register_renderer("mine")
    class MyRenderer(MeshRenderer):
        def __init__(self, image_size=64, camera=None, background_color=BACKGROUND_COLOR):
            rasterizer = MeshRasterizer(image_size, camera=camera, truncate_opaque=True)
            super().__init__(rasterizer, LayeredBlend(0.0), background_color)

or through the ``unicorn.renderers`` entry-point group (``name = "package.module:Class"``), loaded on first use.
A backend that training builds takes ``image_size``, ``camera`` and ``background_color``; one whose constructor
takes ``**kwargs`` gets every option of the ``renderer`` config and checks them itself.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from torch import nn

from unicorn.registry import Registry

__all__ = [
    "RENDERERS",
    "build_renderer",
    "get_renderer_class",
    "list_renderers",
    "register_renderer",
    "unregister_renderer",
]

#: every renderer backend by name (``renderer.name``), with the ``unicorn.renderers`` entry points
RENDERERS: Registry[type[nn.Module]] = Registry("renderer", base=nn.Module, entry_points="unicorn.renderers")

R = TypeVar("R", bound=type[nn.Module])


def register_renderer(name: str, *, overwrite: bool = False) -> Callable[[R], R]:
    """Class decorator registering a renderer backend (an ``nn.Module`` subclass) under ``name``.

    Raises:
        ValueError: ``name`` is taken by another class (``overwrite=True`` replaces it, with a warning).
        TypeError: the class is not an ``nn.Module``.
    """
    return RENDERERS.register(name, overwrite=overwrite)


def unregister_renderer(name: str) -> None:
    """Remove a backend (mostly for tests)."""
    RENDERERS.remove(name)


def list_renderers() -> list[str]:
    """Names of the registered backends, sorted."""
    return RENDERERS.names()


def get_renderer_class(name: str) -> type[nn.Module]:
    """The backend class registered as ``name``.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones listed).
    """
    return RENDERERS.get(name)


def build_renderer(name: str, **options: Any) -> nn.Module:
    """Instantiate the backend ``name`` with keyword ``options``.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name; ``UnknownOptionError``: an option the backend does not
            take (both list what is known).

    Example:
        >>> from unicorn.render import build_renderer
        >>> build_renderer("layered", image_size=32).image_size
        (32, 32)
    """
    return RENDERERS.build(name, options)
