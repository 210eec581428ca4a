"""How a rendered object is put over its background image: variants chosen by name (``model.composite`` on the
command line, ``config["renderer"]["composite"]`` of a model configuration).

- ``"direct"`` (:class:`DirectCompositing`): the background image is the renderer's background, blended where the
  renderer blends (soft edges included).
- ``"reference"`` (:class:`ReferenceCompositing`): render over the renderer's background colour, then
  ``rgb * A + (1 - A) * background``, as the released UNICORN models did.

Without a background image both render over the renderer's background colour. New variants register with
:func:`register_compositing`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import torch
from torch import nn

from unicorn.registry import Registry
from unicorn.render import TexturesUV

__all__ = [
    "Compositing",
    "DirectCompositing",
    "ReferenceCompositing",
    "build_compositing",
    "list_compositings",
    "register_compositing",
]


class Compositing(Protocol):
    """Renders textured meshes over background images: ``(rgb (N, 3, S, S), alpha (N, 1, S, S))``."""

    def __call__(
        self,
        renderer: nn.Module,
        verts: torch.Tensor,
        faces: torch.Tensor,
        textures: TexturesUV,
        R: torch.Tensor,
        T: torch.Tensor,
        background: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]: ...


_COMPOSITINGS: Registry[Compositing] = Registry("compositing")


def register_compositing(name: str, *, overwrite: bool = False) -> Callable[[type], type]:
    """Class decorator: make a compositing (a no-argument constructor) available as ``model.composite=name``
    (``unicorn-train``; ``config["renderer"]["composite"]`` of a model configuration)."""
    return _COMPOSITINGS.register(name, overwrite=overwrite)


def list_compositings() -> list[str]:
    """The registered compositing names, sorted."""
    return _COMPOSITINGS.names()


def build_compositing(name: str) -> Compositing:
    """The compositing registered as ``name``.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones listed).
    """
    return _COMPOSITINGS.build(name)


@register_compositing("direct")
class DirectCompositing:
    """The background image (or the renderer's background colour) is the renderer's background."""

    def __call__(
        self,
        renderer: nn.Module,
        verts: torch.Tensor,
        faces: torch.Tensor,
        textures: TexturesUV,
        R: torch.Tensor,
        T: torch.Tensor,
        background: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        out = renderer(verts, faces, textures, R=R, T=T, background=background)
        return out[:, :3], out[:, 3:]


@register_compositing("reference")
class ReferenceCompositing:
    """Render over the renderer's background colour, then ``rgb * A + (1 - A) * background``."""

    def __call__(
        self,
        renderer: nn.Module,
        verts: torch.Tensor,
        faces: torch.Tensor,
        textures: TexturesUV,
        R: torch.Tensor,
        T: torch.Tensor,
        background: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        out = renderer(verts, faces, textures, R=R, T=T)
        rgb, alpha = out[:, :3], out[:, 3:]
        if background is None:
            return rgb, alpha
        return rgb * alpha + (1 - alpha) * background, alpha
