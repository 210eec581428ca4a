"""The 3D step: the most likely pose candidate rendered with a detached pose."""

from __future__ import annotations

import torch
from torch import nn

from unicorn.model import Unicorn
from unicorn.objectives.losses import MeshRegularizer, ReconstructionLoss
from unicorn.objectives.neighbors import NeighborLoss
from unicorn.objectives.pose_objectives import PoseObjective
from unicorn.objectives.step_losses import StepLosses, with_total

__all__ = ["ShapeStep"]


class ShapeStep(nn.Module):
    """3D-step: ``total = mean_b [L_rec + w_nbr * L_nbr] + w_norm * L_norm + w_lap * L_lap``.

    The pose the pose objective chooses is rendered (:meth:`PoseObjective.shape_pose`: the most likely candidate,
    or with ``sampled`` the candidate it picks, each image's terms weighted).

    Gradients reach the shape, scale, texture and background branches (and their encoders) only. The neighbour
    term is added while it is active (:meth:`NeighborLoss.active`).

    Args:
        reconstruction: the weighted per-sample reconstruction terms.
        regularizer: the weighted mesh regularisers.
        neighbors: the neighbour reconstruction loss and its memory, or None.
        objective: the pose objective, which chooses the rendered pose.
    """

    def __init__(
        self,
        reconstruction: ReconstructionLoss,
        regularizer: MeshRegularizer,
        neighbors: NeighborLoss | None,
        objective: PoseObjective,
    ) -> None:
        super().__init__()
        self.objective = objective
        self.reconstruction, self.regularizer, self.neighbors = reconstruction, regularizer, neighbors

    def forward(
        self,
        model: Unicorn,
        images: torch.Tensor,
        average_texture: bool | torch.Tensor = False,
        iteration: int | None = None,
    ) -> StepLosses:
        """The step's losses on images (B, 3, S, S) in [0, 1].

        Args:
            average_texture: replace every texture by its mean colour (drawn once per batch by the trainer).
            iteration: the training iteration (the pose objective's schedule).

        Returns:
            weighted scalars ``total``, ``rgb``, ``perceptual`` (if enabled), ``neighbor`` (when active),
            ``normal``, ``laplacian``; they sum to ``total``; ``.probs``: the candidate probabilities (K, B) of
            the pose prediction the step rendered with (computed without gradient).
        """
        model.check_images(images)
        branches = model.branches()
        feats = model.encode(images, tuple(b for b in branches if b != "pose"))
        mates = model.encoder_mates("pose")
        with torch.no_grad():
            pose_feats = feats[mates[0]] if mates else model.encode(images, ("pose",))["pose"]
            poses = model.pose(pose_feats.detach())
            R, T, weights = self.objective.shape_pose(poses, iteration)
        pred = model.predict_3d(feats, average_texture)
        verts = pred.verts
        rec, _ = model.render(verts, pred.texture, R, T, pred.background)
        per_sample = self.reconstruction(rec, images)
        if self.neighbors is not None and self.neighbors.active(model):
            per_sample["neighbor"] = self.neighbors(model, images, pred, R, average_texture)
        if weights is not None:
            per_sample = {name: weights * value for name, value in per_sample.items()}
        out = {name: value.mean() for name, value in per_sample.items()}
        out.update(self.regularizer(verts))
        return StepLosses(with_total(out, images), poses.probs)
