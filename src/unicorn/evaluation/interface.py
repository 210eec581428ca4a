"""What evaluation needs from a model: :class:`EvaluableModel`, implemented by :class:`unicorn.model.Unicorn` and by
the baselines (:class:`unicorn.evaluation.baselines.FixedShapeModel`); and which images of a set are scored."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn

from unicorn.model import Prediction
from unicorn.model.template import TemplateMesh
from unicorn.render import TexturesUV

__all__ = ["EvaluableModel", "spread_indices"]


@runtime_checkable
class EvaluableModel(Protocol):
    """A model that :func:`unicorn.evaluation.evaluate`, the report and the renders can score and draw.

    Besides ``nn.Module``'s ``to`` / ``eval``: ``config`` (the model configuration mapping: image size, renderer),
    ``template`` (the mesh topology and UVs), ``renderer``, ``n_candidates`` (pose candidates), ``predict``,
    ``render`` and ``textures``.
    """

    @property
    def config(self) -> Mapping[str, Any]: ...

    @property
    def template(self) -> TemplateMesh: ...

    @property
    def renderer(self) -> nn.Module: ...

    @property
    def n_candidates(self) -> int: ...

    def predict(self, images: torch.Tensor, average_texture: bool = False) -> Prediction:
        """Everything predicted for images (B, 3, S, S) in [0, 1]; ``average_texture``: each texture replaced by its
        mean colour (``unicorn-eval --average-texture``)."""
        ...

    def render(
        self,
        verts: torch.Tensor,
        maps: torch.Tensor,
        R: torch.Tensor,
        T: torch.Tensor,
        background: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """rgb (N, 3, S, S) and alpha (N, 1, S, S) of meshes (N, V, 3) with textures (N, 3, Ht, Wt) at R, T."""
        ...

    def textures(self, maps: torch.Tensor) -> TexturesUV:
        """UV textures of the template for texture images (B, 3, Ht, Wt)."""
        ...

    def to(self, *args: Any, **kwargs: Any) -> Any: ...

    def eval(self) -> Any: ...


def spread_indices(n: int, k: int | None) -> list[int]:
    """``k`` indices spread evenly over ``range(n)`` (all of them when ``k`` is None or >= n)."""
    if k is None or k >= n:
        return list(range(n))
    if k < 1:
        raise ValueError(f"need at least one image, got max_images={k}")
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64)).tolist()
