"""Reference baselines of the quality benchmark: what a model must beat to have learned anything.

- :func:`template_baseline`: the untrained template (UNICORN's ellipsoid) at the anchor pose of the first pose
  candidate, for every image. A model whose numbers are no better has learned neither shape nor pose.
- :func:`fit_silhouettes`: one object's template fitted to the masks of all its views at their ground-truth poses:
  what the silhouettes alone tell about a shape (the floor of a method that learns shape from silhouettes and
  colours at that image size, with the model's regularisers), scored against the object's 3D ground truth.
- :func:`mean_shape_baseline`: the single mesh (template topology) closest on average to the training shapes
  (:func:`fit_mean_shape`), placed with a pose supplied by the caller. Evaluated with
  ``EvalOptions(oracle_pose=True)``, i.e. with the ground-truth pose, it is the best one can do with one shape
  for every image and a perfect pose: generous to the baseline, so a model beating it on ``chamfer-L1`` does
  reconstruct per-image shape.

Both are :class:`FixedShapeModel` instances, which :func:`~unicorn.evaluation.evaluate` scores unchanged.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn
from tqdm.auto import tqdm

from unicorn.checks import check_faces
from unicorn.data.shapenet import ShapeNetNMR
from unicorn.evaluation.interface import spread_indices
from unicorn.metrics import NearestNeighborIndex, gather_points, mask_iou, sample_points_from_meshes
from unicorn.model import Prediction, Unicorn
from unicorn.model.losses import NormalConsistencyLoss, UniformLaplacianLoss
from unicorn.model.template import TemplateMesh
from unicorn.render import TexturesUV

__all__ = [
    "POSE_MODES",
    "FixedShapeModel",
    "fit_mean_shape",
    "fit_silhouettes",
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
        V = model.template.num_verts
        if not isinstance(verts, torch.Tensor) or verts.shape != (V, 3):
            shape = tuple(verts.shape) if isinstance(verts, torch.Tensor) else type(verts).__name__
            raise ValueError(f"verts must be a ({V}, 3) tensor on the model's template topology, got {shape}")
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


# ---------------------------------------------------------------------------------------------- the mean shape
def _stack_clouds(
    point_clouds: Sequence[torch.Tensor] | torch.Tensor,
    num_points: int,
    generator: torch.Generator,
    device: torch.device,
    dtype: torch.dtype,
) -> torch.Tensor:
    """(M, num_points, 3): each cloud subsampled without replacement, or (if smaller) padded by resampling."""
    if isinstance(point_clouds, torch.Tensor):
        if point_clouds.dim() != 3 or point_clouds.shape[-1] != 3:
            raise ValueError(f"a point-cloud tensor must have shape (M, N, 3), got {tuple(point_clouds.shape)}")
        clouds = list(point_clouds)
    else:
        clouds = list(point_clouds)
    if not clouds:
        raise ValueError("point_clouds is empty: there is no shape to fit")
    out = []
    for i, cloud in enumerate(clouds):
        cloud = torch.as_tensor(cloud)
        if cloud.dim() != 2 or cloud.shape[1] != 3 or cloud.shape[0] == 0:
            raise ValueError(f"point cloud {i} must have shape (N, 3) with N >= 1, got {tuple(cloud.shape)}")
        if not bool(torch.isfinite(cloud).all()):
            raise ValueError(f"point cloud {i} has non-finite coordinates")
        n = cloud.shape[0]
        if n >= num_points:
            keep = torch.randperm(n, generator=generator)[:num_points]
        else:
            # every point once, then uniform draws: the mean distance to the cloud stays unbiased
            keep = torch.cat([torch.arange(n), torch.randint(n, (num_points - n,), generator=generator)])
        out.append(cloud[keep].to(device=device, dtype=dtype))
    return torch.stack(out)


def fit_mean_shape(
    template_verts: torch.Tensor,
    faces: torch.Tensor,
    point_clouds: Sequence[torch.Tensor] | torch.Tensor,
    iterations: int = 300,
    lr: float = 0.01,
    num_points: int = 2000,
    smooth_weight: float = 0.1,
    normal_weight: float = 0.01,
    shapes_per_step: int = 16,
    seed: int = 0,
    progress: bool = False,
) -> torch.Tensor:
    """The single mesh (template topology) closest on average to a set of shapes, in their object frame.

    Per-vertex offsets of the template are optimised with Adam (learning rate cosine-annealed to a tenth) to
    minimise ``mean_shapes chamfer_L1(mesh, shape) + smooth_weight * laplacian + normal_weight * normal``, where
    ``chamfer_L1`` is the symmetric mean nearest-neighbour distance ``(accuracy + completeness) / 2`` (no x10
    factor) between ``num_points`` area-uniform samples of the mesh (redrawn every iteration, differentiable
    w.r.t. the vertices) and the shape's points, and the regularisers are the training losses
    :class:`~unicorn.model.losses.UniformLaplacianLoss` and :class:`~unicorn.model.losses.NormalConsistencyLoss`,
    which keep the mesh smooth and unfolded. Each iteration uses a random mini-batch of ``shapes_per_step``
    shapes (all of them when there are fewer).

    Args:
        template_verts: (V, 3) initial vertices (e.g. ``model.template.verts``); the fit runs on their device.
        faces: (F, 3) integer faces of a closed manifold mesh (the normal regulariser needs one).
        point_clouds: the M shapes, in the frame the mesh is wanted in: a sequence of (N_i, 3) tensors or one
            (M, N, 3) tensor. Each is subsampled to ``num_points`` once (padded by resampling if smaller).
        iterations: Adam steps (0 returns the template).
        lr: initial Adam learning rate, in object units per step.
        num_points: points sampled on the mesh per iteration and kept per shape.
        smooth_weight: weight of the uniform Laplacian regulariser.
        normal_weight: weight of the normal-consistency regulariser.
        shapes_per_step: shapes per iteration.
        seed: seed of the subsampling, the mini-batches and the surface samples.
        progress: show a progress bar.

    Returns:
        (V, 3) fitted vertices (detached), on the template's device and dtype.

    Raises:
        ValueError: malformed template, faces or clouds, no clouds, or invalid settings.
    """
    if not isinstance(template_verts, torch.Tensor) or template_verts.dim() != 2 or template_verts.shape[1] != 3:
        shape = tuple(template_verts.shape) if isinstance(template_verts, torch.Tensor) else type(template_verts)
        raise ValueError(f"template_verts must have shape (V, 3), got {shape}")
    if not template_verts.dtype.is_floating_point or not bool(torch.isfinite(template_verts).all()):
        raise ValueError("template_verts must be finite floating-point coordinates")
    V = template_verts.shape[0]
    check_faces(faces, V)
    if iterations < 0 or num_points < 1 or shapes_per_step < 1:
        raise ValueError(
            f"need iterations >= 0, num_points >= 1 and shapes_per_step >= 1, got {iterations}, {num_points}, "
            f"{shapes_per_step}"
        )
    if not lr > 0 or smooth_weight < 0 or normal_weight < 0:
        raise ValueError(f"need lr > 0 and non-negative weights, got {lr}, {smooth_weight}, {normal_weight}")
    device, dtype = template_verts.device, template_verts.dtype
    generator = torch.Generator().manual_seed(int(seed))  # CPU draws: the same fit on every device
    clouds = _stack_clouds(point_clouds, num_points, generator, device, dtype)  # (M, N, 3)
    M = clouds.shape[0]
    faces = faces.long().to(device)
    base = template_verts.detach()
    if iterations == 0:
        return base.clone()

    targets = NearestNeighborIndex(clouds)  # the shapes' search structures, built once for every iteration
    laplacian = UniformLaplacianLoss(faces, V).to(device)
    normal = NormalConsistencyLoss(faces).to(device)
    offsets = torch.zeros_like(base, requires_grad=True)
    optimizer = torch.optim.Adam([offsets], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, iterations, eta_min=0.1 * lr)
    b = min(shapes_per_step, M)
    bar = tqdm(range(iterations), desc="mean shape", unit="it", disable=not progress)
    with torch.enable_grad():  # callers may be under no_grad (e.g. inside an evaluation)
        for _ in bar:
            pick = torch.randperm(M, generator=generator)[:b].to(device) if b < M else None
            target = clouds if pick is None else clouds[pick]  # (b, N, 3)
            verts = (base + offsets).unsqueeze(0)  # (1, V, 3)
            points, _ = sample_points_from_meshes(verts, faces, num_points, generator=generator)
            chamfer = _sample_chamfer(points, target, targets if pick is None else targets.select(pick))
            loss = chamfer + smooth_weight * laplacian(verts) + normal_weight * normal(verts)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
            if progress:
                bar.set_postfix(chamfer=f"{float(chamfer):.4f}")
    return (base + offsets).detach()


def _sample_chamfer(points: torch.Tensor, target: torch.Tensor, index: NearestNeighborIndex) -> torch.Tensor:
    """``chamfer_l1(points.expand(b, -1, -1), target, factor=1.0).mean()``, the same operations (the fit's samples
    depend on every rounding of it), for one sample (1, N, 3) of a mesh against b shapes (b, N', 3) with their
    ``index``: the shapes' trees are reused, and their points are searched in one tree of the sample."""
    b = target.shape[0]
    expanded = points.expand(b, -1, -1)
    d_pred, _ = index.query(expanded)
    idx_gt = NearestNeighborIndex(points.detach()).indices(target.reshape(1, -1, 3)).view(b, -1)
    d_gt = torch.linalg.vector_norm(target - gather_points(expanded, idx_gt), dim=-1)
    factor = 1.0
    return (factor * 0.5 * (d_pred.mean(dim=1) + d_gt.mean(dim=1))).mean()


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
        ValueError: malformed masks or cameras, or invalid settings.
    """
    size = int(model.config["image_size"])
    if not isinstance(masks, torch.Tensor) or masks.dim() != 4 or masks.shape[1:] != (1, size, size):
        shape = tuple(masks.shape) if isinstance(masks, torch.Tensor) else type(masks)
        raise ValueError(f"masks must have shape (N, 1, {size}, {size}) at the model's image size, got {shape}")
    N = masks.shape[0]
    if N == 0 or R.shape != (N, 3, 3) or T.shape != (N, 3):
        raise ValueError(f"need N >= 1 views with R (N, 3, 3) and T (N, 3), got {tuple(R.shape)} and {tuple(T.shape)}")
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
