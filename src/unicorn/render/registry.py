"""Registry of renderer backends, by name.

This is the one list of the backends. Backends are ``nn.Module`` classes whose constructor takes keyword
options and whose ``forward`` follows :class:`unicorn.render.MeshRenderer`; the built-in ones
(:mod:`unicorn.render.backends`) are named compositions of a rasterizer and an aggregator. Another package
registers its own with the decorator::

    @register_renderer("mine")
    class MyRenderer(MeshRenderer):
        def __init__(self, image_size=64, background_color=(1.0, 1.0, 1.0)):
            super().__init__(MeshRasterizer(image_size, truncate_opaque=True), LayeredBlend(0.0), background_color)

or through the ``unicorn.renderers`` entry-point group (``name = "package.module:Class"``), loaded on first use.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any, TypeVar

from torch import nn

__all__ = [
    "build_renderer",
    "get_renderer_class",
    "list_renderers",
    "register_renderer",
    "unregister_renderer",
]

_ENTRY_POINT_GROUP = "unicorn.renderers"
_REGISTRY: dict[str, type[nn.Module]] = {}
_entry_points_loaded = False

R = TypeVar("R", bound=type[nn.Module])


def register_renderer(name: str, *, overwrite: bool = False) -> Callable[[R], R]:
    """Class decorator registering a renderer backend under ``name``."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"renderer name must be a non-empty string, got {name!r}")

    def decorator(cls: R) -> R:
        if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
            raise TypeError(f"a renderer backend must be an nn.Module subclass, got {cls!r}")
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            if not overwrite:
                raise KeyError(
                    f"renderer {name!r} is already registered ({_REGISTRY[name].__qualname__}); "
                    "pass overwrite=True to replace it"
                )
            warnings.warn(f"replacing renderer {name!r}", stacklevel=2)
        _REGISTRY[name] = cls
        return cls

    return decorator


def unregister_renderer(name: str) -> None:
    """Remove a backend (mostly for tests)."""
    _REGISTRY.pop(name, None)


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for ep in entry_points(group=_ENTRY_POINT_GROUP):
        if ep.name in _REGISTRY:
            continue
        try:
            register_renderer(ep.name)(ep.load())
        except Exception as err:  # a broken plugin must not break the built-in backends
            warnings.warn(f"could not load renderer entry point {ep.name!r} ({ep.value}): {err}", stacklevel=2)


def list_renderers() -> list[str]:
    """Names of the registered backends, sorted."""
    _load_entry_points()
    return sorted(_REGISTRY)


def get_renderer_class(name: str) -> type[nn.Module]:
    """The backend class registered as ``name``."""
    _load_entry_points()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown renderer {name!r}; available: {', '.join(sorted(_REGISTRY))}") from None


def build_renderer(name: str, **options: Any) -> nn.Module:
    """Instantiate the backend ``name`` with keyword ``options``.

    Example:
        >>> from unicorn.render import build_renderer
        >>> build_renderer("layered", image_size=32).image_size
        (32, 32)
    """
    cls = get_renderer_class(name)
    try:
        return cls(**options)
    except TypeError as err:
        raise TypeError(f"bad options for renderer {name!r}: {err}") from err
