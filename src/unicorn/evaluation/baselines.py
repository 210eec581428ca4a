"""Reference baselines of the quality benchmark: what a model must beat to have learned anything.

- :func:`template_baseline`: the untrained template (UNICORN's ellipsoid) at the anchor pose of the first pose
  candidate, for every image. A model whose numbers are no better has learned neither shape nor pose.
- :func:`fit_silhouettes`: one object's template fitted to the masks of all its views at their ground-truth poses:
  what the silhouettes alone tell about a shape (the floor of a method that learns shape from silhouettes and
  colours at that image size, with the model's regularisers), scored against the object's 3D ground truth.
- :func:`mean_shape_baseline`: the single mesh (template topology) closest on average to the training shapes
  (:func:`~unicorn.evaluation.mean_shape.fit_mean_shape`), placed with a pose supplied by the caller. Evaluated with
  ``EvalOptions(oracle_pose=True)``, i.e. with the ground-truth pose, it is the best one can do with one shape
  for every image and a perfect pose: generous to the baseline, so a model beating it on ``chamfer-L1`` does
  reconstruct per-image shape.

The template and the mean shape are :class:`FixedShapeModel` instances, which :func:`~unicorn.evaluation.evaluate`
scores unchanged; :func:`fit_silhouettes` returns the fitted vertices and their mask IoU.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from unicorn.checks import check_shape
from unicorn.data.shapenet import ShapeNetNMR, read_metadata, resolve_categories
from unicorn.evaluation.evaluator import category_group
from unicorn.evaluation.interface import spread_indices
from unicorn.evaluation.mean_shape import fit_mean_shape
from unicorn.metrics import mask_iou
from unicorn.model import Prediction, Unicorn
from unicorn.model.template import TemplateMesh
from unicorn.objectives.losses import NormalConsistencyLoss, UniformLaplacianLoss
from unicorn.render import TexturesUV

__all__ = [
    "POSE_MODES",
    "FixedShapeModel",
    "fit_silhouettes",
    "category_point_clouds",
    "mean_shape_baseline",
    "template_baseline",
    "training_point_clouds",
]

#: pose of a :class:`FixedShapeModel`: the first candidate's anchor (no offsets), or the wrapped model's own
POSE_MODES = ("anchor", "predicted")


class FixedShapeModel(nn.Module):
    """A :class:`~unicorn.model.Unicorn` whose shape (and optionally pose) predictions are replaced by fixed ones.

    Texture, background and pose candidates still come from the wrapped model, so :func:`evaluate` (and the
    rendering helpers) score it like any model: it is an :class:`~unicorn.evaluation.interface.EvaluableModel`
    whose members delegate to the wrapped model (a registered submodule, so ``.to()`` / ``.eval()`` reach it).

    Args:
        model: the wrapped model.
        verts: (V, 3) the fixed object-frame mesh, on the template's topology (V = ``model.template.num_verts``).
        pose: ``"anchor"``: every image at the anchor pose of candidate 0 with zero offsets (the pose head's
            anchor angles and prior translation), all candidates at their anchors and probability 1 on
            candidate 0; ``"predicted"``: the wrapped model's candidates and selected pose.

    Raises:
        TypeError: ``model`` is not a :class:`~unicorn.model.Unicorn`.
        ValueError: ``verts`` is not a finite (V, 3) tensor matching the template, or ``pose`` is unknown.
    """

    fixed_verts: torch.Tensor

    def __init__(self, model: Unicorn, verts: torch.Tensor, pose: str = "anchor") -> None:
        super().__init__()
        if not isinstance(model, Unicorn):
            raise TypeError(f"model must be a unicorn.model.Unicorn, got {type(model).__name__}")
        if pose not in POSE_MODES:
            raise ValueError(f"pose must be one of {POSE_MODES}, got {pose!r}")
        check_shape(verts, "V, 3", "verts", {"V": model.template.num_verts})
        if not bool(torch.isfinite(verts).all()):
            raise ValueError("verts must be finite")
        self.model = model
        self.pose_mode = pose
        ref = model.template.verts
        self.register_buffer("fixed_verts", verts.detach().to(device=ref.device, dtype=ref.dtype).clone())

    # ------------------------------------------------------------------ what evaluate() and the renders use
    @property
    def config(self) -> dict:
        return self.model.config

    @property
    def template(self) -> TemplateMesh:
        return self.model.template

    @property
    def renderer(self) -> nn.Module:
        return self.model.renderer

    @property
    def n_candidates(self) -> int:
        return self.model.n_candidates

    def textures(self, maps: torch.Tensor) -> TexturesUV:
        """The wrapped model's UV textures for texture images (B, 3, Ht, Wt)."""
        return self.model.textures(maps)

    def render(
        self,
        verts: torch.Tensor,
        maps: torch.Tensor,
        R: torch.Tensor,
        T: torch.Tensor,
        background: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The wrapped model's :meth:`~unicorn.model.Unicorn.render`: rgb (N, 3, S, S) and alpha (N, 1, S, S)."""
        return self.model.render(verts, maps, R, T, background)

    # ------------------------------------------------------------------ predictions
    def predict(self, images: torch.Tensor, average_texture: bool = False) -> Prediction:
        """The wrapped model's prediction with the fixed shape (and, with ``pose="anchor"``, the anchor pose).

        Args:
            images: (B, 3, S, S) in [0, 1].
            average_texture: mean-colour textures, as :meth:`~unicorn.model.Unicorn.predict`.

        Returns:
            :class:`~unicorn.model.Prediction` with ``verts`` = ``canonical_verts`` = the fixed mesh (B, V, 3),
            ``scale`` ones (B, 3), and ``poses`` / ``R`` (B, 3, 3) / ``T`` (B, 3) as set by the pose mode; codes,
            texture and background are the wrapped model's (``shape_code`` no longer drives the shape).
        """
        pred = self.model.predict(images, average_texture=average_texture)
        B = images.shape[0]
        verts = self.fixed_verts.unsqueeze(0).expand(B, -1, -1).clone()
        scale = torch.ones(B, 3, dtype=verts.dtype, device=verts.device)
        poses, R, T = pred.poses, pred.R, pred.T
        if self.pose_mode == "anchor":
            poses = self.model.pose.anchor_poses(B)
            R, T = poses.select()
        return dataclasses.replace(pred, canonical_verts=verts, scale=scale, verts=verts, poses=poses, R=R, T=T)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, Prediction]:
        """Reconstruct images (B, 3, S, S): ``(rec (B, 3, S, S), prediction)``, like the wrapped model."""
        pred = self.predict(images)
        rec, _ = self.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
        return rec, pred

    def extra_repr(self) -> str:
        return f"pose={self.pose_mode!r}, V={self.fixed_verts.shape[0]}"


def template_baseline(model: Unicorn) -> FixedShapeModel:
    """The untrained template (``model.template.verts``, UNICORN's ellipsoid) at the anchor pose of candidate 0."""
    return FixedShapeModel(model, model.template.verts, pose="anchor")


def fit_silhouettes(
    model: Unicorn,
    masks: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    iterations: int = 300,
    lr: float = 0.01,
    regularisation: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's template deformed to match one object's silhouettes, seen from known cameras.

    Per-vertex offsets of ``model.template`` are optimised with Adam to minimise the mean squared error between
    the renderer's alpha (``model.render``, the model's own soft rasteriser at its image size) and the masks, plus
    the model's normal-consistency and Laplacian regularisers at its training weights times ``regularisation``.
    With the masks of every view of an object and its ground-truth cameras, the result is what silhouettes can say
    about that shape at this resolution: no pose error, no generalisation gap, no texture. Its Chamfer distance to
    the 3D ground truth is a floor for models that learn shape from images (concavities that no silhouette shows,
    such as the underside of a car between its wheels, stay filled).

    Args:
        model: the model whose template, renderer and regularisers are used (its weights are not).
        masks: (N, 1, S, S) target silhouettes in [0, 1], S the model's ``image_size``.
        R: (N, 3, 3) world-to-view rotations of the views (the datasets' ``R``).
        T: (N, 3) their translations.
        iterations: Adam steps (0 returns the template).
        lr: Adam learning rate, in object units per step.
        regularisation: factor on the model's ``normal_weight`` and ``laplacian_weight``.

    Returns:
        (V, 3) fitted object-frame vertices (detached) and the (N,) mask IoU of their renders (alpha > 0.5).

    Raises:
        ShapeError: masks, R and T not of the shapes above.
        ValueError: no views, or invalid settings.
    """
    dims = check_shape(masks, "N, 1, S, S", "masks", {"S": int(model.config["image_size"])})
    check_shape(R, "N, 3, 3", "R", dims)
    check_shape(T, "N, 3", "T", dims)
    N = dims["N"]
    if N == 0:
        raise ValueError("need N >= 1 views, got none")
    if iterations < 0 or not lr > 0 or regularisation < 0:
        raise ValueError(
            f"need iterations >= 0, lr > 0 and regularisation >= 0, got {iterations}, {lr}, {regularisation}"
        )
    weights = model.config["loss"]
    base = model.template.verts.detach()
    masks, R, T = (x.to(base) for x in (masks, R, T))
    maps = torch.full((N, 3, 4, 4), 0.5, device=base.device, dtype=base.dtype)  # the alpha ignores the colour
    offsets = torch.zeros_like(base, requires_grad=True)
    optimizer = torch.optim.Adam([offsets], lr=lr)
    normal_loss = NormalConsistencyLoss(model.template.faces).to(base.device)
    laplacian_loss = UniformLaplacianLoss(model.template.faces, model.template.num_verts).to(base.device)
    with torch.enable_grad():  # callers may be under no_grad
        for _ in range(iterations):
            verts = (base + offsets).unsqueeze(0)
            _, alpha = model.render(verts.expand(N, -1, -1), maps, R, T)
            loss = torch.nn.functional.mse_loss(alpha, masks) + regularisation * (
                weights["normal_weight"] * normal_loss(verts) + weights["laplacian_weight"] * laplacian_loss(verts)
            )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
    verts = (base + offsets).detach()
    with torch.no_grad():
        _, alpha = model.render(verts.unsqueeze(0).expand(N, -1, -1), maps, R, T)
    return verts, mask_iou(alpha, masks, reduction="none")


def mean_shape_baseline(
    model: Unicorn, point_clouds: Sequence[torch.Tensor] | torch.Tensor, **fit_kwargs: Any
) -> FixedShapeModel:
    """The mean shape of ``point_clouds`` (:func:`fit_mean_shape` from the model's template) as a baseline.

    Its pose is the wrapped model's prediction (``pose="predicted"``), but it is meant to be evaluated with
    ``EvalOptions(oracle_pose=True)``, i.e. rendered and aligned at the ground-truth pose: the best one could do
    with a single shape for every image and a perfect pose, which is generous to the baseline.

    Args:
        model: the model whose template, texture and renderer the baseline uses.
        point_clouds: training shapes in the ground-truth object frame (e.g. :func:`training_point_clouds`).
        **fit_kwargs: options of :func:`fit_mean_shape`.
    """
    verts = fit_mean_shape(model.template.verts, model.template.faces, point_clouds, **fit_kwargs)
    return FixedShapeModel(model, verts, pose="predicted")


def training_point_clouds(
    root: str | os.PathLike,
    categories: str | list[str] | None = None,
    max_models: int | None = None,
    num_points: int | None = None,
) -> list[torch.Tensor]:
    """Ground-truth point clouds of the train split of a ShapeNet-NMR (or synthetic) dataset, one per model.

    Args:
        root: the dataset root (holds ``metadata.yaml``; for ``synthetic``, the generated dataset).
        categories: category names or synsets, None for all.
        max_models: at most this many models, spread evenly over the split (so every category is represented).
        num_points: keep this many points per model (a fixed subset per model), None for all.

    Returns:
        M clouds (N_i, 3) float32 in UNICORN's object frame (the frame of the datasets' ``R`` / ``T``).
    """
    dataset = ShapeNetNMR(root, categories, "train", views="random", with_points=True, n_points=num_points)
    models = spread_indices(len(dataset.models), max_models)
    return [dataset.load_points(m)[0] for m in models]


def category_point_clouds(
    root: str | os.PathLike,
    categories: str | list[str] | None = None,
    max_models: int | None = None,
    num_points: int | None = None,
) -> dict[str, list[torch.Tensor]]:
    """:func:`training_point_clouds` of each category, by the group :func:`~unicorn.evaluation.evaluate` scores
    its objects in (:func:`~unicorn.evaluation.evaluator.category_group`: the category's name; categories that
    share it are one group).

    Args:
        root, categories, num_points: as :func:`training_point_clouds`.
        max_models: at most this many models per group.

    Returns:
        group name -> its M clouds (N_i, 3), in the order of the categories.
    """
    metadata = read_metadata(Path(root))
    synsets: dict[str, list[str]] = {}
    for synset in resolve_categories(metadata, categories):
        synsets.setdefault(category_group(metadata, synset), []).append(synset)
    return {group: training_point_clouds(root, ids, max_models, num_points) for group, ids in synsets.items()}
