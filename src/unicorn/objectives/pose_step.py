"""The pose step (P-step): all K pose candidates rendered with detached shapes, textures and backgrounds.

How the candidates' reconstruction losses train the pose probabilities is a pose objective, chosen by name
(``loss.pose_objective``; :mod:`unicorn.objectives.pose_objectives`); whether the pose branch also learns from the
model's renders at drawn viewpoints is a viewpoint supervision (``loss.viewpoint``;
:mod:`unicorn.objectives.viewpoint`).
"""

from __future__ import annotations

import torch
from torch import nn

from unicorn.data.augment import random_roll_shift
from unicorn.model import Unicorn
from unicorn.model.autoencoder import Prediction3D
from unicorn.objectives.losses import (
    ReconstructionLoss,
    candidate_spacing_loss,
    flip_consistency_loss,
    uniform_pose_prior,
    view_equivariance_loss,
)
from unicorn.objectives.pose_objectives import PoseObjective
from unicorn.objectives.step_losses import StepLosses, with_total
from unicorn.objectives.viewpoint import ViewpointSupervision

__all__ = ["PoseStep"]


class PoseStep(nn.Module):
    """P-step: the pose candidates rendered with the detached 3D prediction; gradients reach the pose branch only.

    The pose objective renders the candidates it chooses (:meth:`PoseObjective.pose_terms`: every one, or with
    ``sampled`` the one it picks per image).
    ``total = objective(p, L_rec) + uniform_weight * L_uni + spacing_weight * L_spacing + flip_weight * L_flip
    [+ viewpoint terms]`` (:func:`uniform_pose_prior`, :func:`candidate_spacing_loss`, :func:`flip_consistency_loss`,
    :class:`~unicorn.objectives.viewpoint.ViewpointSupervision`); the rotation, translation and probability heads and
    the encoder that feeds them receive gradients.

    Args:
        reconstruction: the weighted per-sample reconstruction terms.
        objective: how the candidates' terms are weighted (:class:`ExpectedLoss`, :class:`AssignedLoss`, ...).
        uniform_weight: weight of the candidate-balance prior (<= 0: left out); uniform_reduction: its reduction.
        spacing_weight: weight of the candidates' spacing term (<= 0: left out, the paper); spacing_angle: the
            angle in degrees from which a pair of candidates adds nothing to it.
        viewpoint: the viewpoint supervision from renders at drawn views, or None (the paper).
        flip_weight: weight of the flipped images' pose consistency (<= 0: left out, the paper); it encodes the
            flipped batch once more with the pose branch's encoder.
        equivariance_weight: weight of the rolled and shifted images' pose equivariance (<= 0: left out, the
            paper; :func:`view_equivariance_loss`); it encodes the batch, each image rolled by up to
            ``equivariance_roll`` degrees and shifted by up to ``equivariance_shift`` (NDC), once more with the pose
            branch's encoder.
    """

    def __init__(
        self,
        reconstruction: ReconstructionLoss,
        objective: PoseObjective,
        uniform_weight: float,
        uniform_reduction: str = "sum",
        spacing_weight: float = 0.0,
        spacing_angle: float = 30.0,
        viewpoint: ViewpointSupervision | None = None,
        flip_weight: float = 0.0,
        equivariance_weight: float = 0.0,
        equivariance_roll: float = 15.0,
        equivariance_shift: float = 0.1,
    ) -> None:
        super().__init__()
        self.flip_weight = flip_weight
        self.equivariance_weight, self.equivariance_roll = equivariance_weight, equivariance_roll
        self.equivariance_shift = equivariance_shift
        self.viewpoint = viewpoint
        self.reconstruction, self.objective = reconstruction, objective
        self.uniform_weight, self.uniform_reduction = uniform_weight, uniform_reduction
        self.spacing_weight, self.spacing_angle = spacing_weight, spacing_angle

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
            iteration: the training iteration (the viewpoint supervision's schedule; None: it is active).

        Returns:
            weighted scalars ``total``, ``rgb``, ``perceptual`` (if enabled), the objective's terms, ``uniform``,
            ``spacing`` and ``flip`` (if enabled) and the viewpoint supervision's (when active; they sum to ``total``);
            ``.probs``: the candidate probabilities (K, B), detached; ``.stats``: the viewpoint supervision's.
        """
        model.check_images(images)
        branches = model.branches()
        with_pose = ("pose", *model.encoder_mates("pose"))
        feats = model.encode(images, with_pose)
        with torch.no_grad():
            # detached 3D branches: computing those of the other encoders without autograd is the same and cheaper
            other = {**feats, **model.encode(images, tuple(b for b in branches if b not in with_pose))}
            other = {k: v.detach() for k, v in other.items()}
            p = model.predict_3d(other, average_texture)
        poses = model.pose(feats["pose"])
        out = self.objective.pose_terms(poses, lambda R, T, n: self._terms(model, images, p, R, T, n), iteration)
        if self.uniform_weight > 0:
            out["uniform"] = self.uniform_weight * uniform_pose_prior(poses.probs, self.uniform_reduction)
        if self.spacing_weight > 0:
            out["spacing"] = self.spacing_weight * candidate_spacing_loss(poses.R, self.spacing_angle)
        if self.flip_weight > 0:
            flipped = model.pose(model.encode(images.flip(-1), ("pose",))["pose"])
            out["flip"] = self.flip_weight * flip_consistency_loss(poses, flipped, model.pose.mirror_index())
        if self.equivariance_weight > 0:
            moved_images, roll, shift = random_roll_shift(images, self.equivariance_roll, self.equivariance_shift)
            moved = model.pose(model.encode(moved_images, ("pose",))["pose"])
            f = model.renderer.camera.focal_length
            out["equivariance"] = self.equivariance_weight * view_equivariance_loss(
                poses, moved, roll, shift, model.pose, f
            )
        stats: dict[str, torch.Tensor] = {}
        if self.viewpoint is not None and self.viewpoint.active(iteration):
            terms, stats = self.viewpoint(model, p)
            out.update(terms)
        return StepLosses(with_total(out, images), poses.probs.detach(), stats)

    def _terms(
        self, model: Unicorn, images: torch.Tensor, p: Prediction3D, R: torch.Tensor, T: torch.Tensor, n: int
    ) -> dict[str, torch.Tensor]:
        """Reconstruction terms (n * B,) of the detached prediction rendered at n poses per image: R (n * B, 3, 3),
        T (n * B, 3), pose-major."""
        verts = p.verts.repeat(n, 1, 1)
        bkg = None if p.background is None else p.background.repeat(n, 1, 1, 1)
        targets = images.repeat(n, 1, 1, 1)
        rec, _ = model.render(verts, p.texture.repeat(n, 1, 1, 1), R, T, bkg)
        return self.reconstruction(rec, targets)
