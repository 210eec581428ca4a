"""The pose step (P-step): all K pose candidates rendered with detached shapes, textures and backgrounds.

How the candidates' reconstruction losses train the pose probabilities is a pose objective, chosen by name
(``loss.pose_objective``):

- ``"expected"`` (:class:`ExpectedLoss`, the paper's): ``mean_b sum_k p[k, b] * L_rec(k, b)``;
- ``"assigned"`` (:class:`AssignedLoss`): the same sum with ``p`` detached, and the probabilities learn which
  candidate reconstructs best from ``assignment_weight * candidate_assignment_loss`` (term ``assignment``);
- ``"assigned_best"`` (:class:`AssignedBestLoss`): as ``"assigned"``, with only the best-reconstructing
  candidate's pose refined (weight 1 for it, 0 for the others).

New objectives register with :func:`register_pose_objective`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch
from torch import nn

from unicorn.model import Unicorn
from unicorn.model.losses import (
    ReconstructionLoss,
    candidate_assignment_loss,
    candidate_spacing_loss,
    uniform_pose_prior,
)
from unicorn.objectives.step_losses import StepLosses, with_total
from unicorn.registry import Registry

__all__ = [
    "AssignedBestLoss",
    "AssignedLoss",
    "ExpectedLoss",
    "PoseObjective",
    "PoseStep",
    "build_pose_objective",
    "list_pose_objectives",
    "register_pose_objective",
]


class PoseObjective(Protocol):
    """Turns per-candidate reconstruction terms into the pose step's weighted terms.

    Called with the candidates' probabilities ``probs`` and ``log_probs`` (K, B) and the reconstruction terms
    (name -> (K * B,), candidate-major); returns scalar terms.
    """

    def __call__(
        self, probs: torch.Tensor, log_probs: torch.Tensor, terms: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]: ...


_POSE_OBJECTIVES: Registry[PoseObjective] = Registry("pose objective", key="pose_objective")


def register_pose_objective(name: str) -> Callable[[type], type]:
    """Class decorator: make a pose objective available as ``loss.pose_objective=name``; its constructor receives
    the options of the ``loss`` group it names (e.g. ``assignment_weight``)."""
    return _POSE_OBJECTIVES.register(name)


def list_pose_objectives() -> list[str]:
    """The registered pose-objective names, sorted."""
    return _POSE_OBJECTIVES.names()


def build_pose_objective(name: str, **options: Any) -> PoseObjective:
    """The pose objective registered as ``name``, built from the options its constructor names.

    Raises:
        ValueError: an unknown name (the known ones listed).
    """
    return _POSE_OBJECTIVES.build(name, **options)


def _weighted(weights: torch.Tensor, terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``mean_b sum_k weights[k, b] * term[k, b]`` of every term (K * B,)."""
    K, B = weights.shape
    return {name: (weights * value.view(K, B)).sum(0).mean() for name, value in terms.items()}


@register_pose_objective("expected")
class ExpectedLoss:
    """The paper's expected reconstruction loss: gradients reach the probabilities through ``p``."""

    def __call__(
        self, probs: torch.Tensor, log_probs: torch.Tensor, terms: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        return _weighted(probs, terms)


@register_pose_objective("assigned")
class AssignedLoss:
    """Detached weights ``p``; the probabilities learn the best candidate (:func:`candidate_assignment_loss`).

    Args:
        assignment_weight: weight of the cross-entropy term ``assignment``.
    """

    def __init__(self, assignment_weight: float) -> None:
        self.assignment_weight = assignment_weight

    def weights(self, probs: torch.Tensor, per_candidate: torch.Tensor) -> torch.Tensor:
        """(K, B) weights of the candidates' terms from the probabilities and the summed terms, both (K, B)."""
        return probs.detach()

    def __call__(
        self, probs: torch.Tensor, log_probs: torch.Tensor, terms: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        if not terms:
            return {}
        per_candidate = torch.stack(list(terms.values())).sum(0).view(probs.shape)
        out = _weighted(self.weights(probs, per_candidate.detach()), terms)
        out["assignment"] = self.assignment_weight * candidate_assignment_loss(log_probs, per_candidate)
        return out


@register_pose_objective("assigned_best")
class AssignedBestLoss(AssignedLoss):
    """As :class:`AssignedLoss`, with weight 1 for the best-reconstructing candidate and 0 for the others: only
    that candidate's pose is refined. (Weighted by the probabilities, every candidate's pose is also pulled towards
    the pose the detached reconstruction was fitted to, the selected candidate's.)

    Args:
        assignment_weight: weight of the cross-entropy term ``assignment``.
    """

    def weights(self, probs: torch.Tensor, per_candidate: torch.Tensor) -> torch.Tensor:
        best = per_candidate.argmin(0)  # (B,)
        return torch.nn.functional.one_hot(best, probs.shape[0]).T.to(probs.dtype)


class PoseStep(nn.Module):
    """P-step: every candidate rendered with the detached 3D prediction; gradients reach the pose branch only.

    ``total = objective(p, L_rec) + uniform_weight * L_uni + spacing_weight * L_spacing``
    (:func:`uniform_pose_prior`, :func:`candidate_spacing_loss`); the rotation, translation and probability heads
    and the encoder that feeds them receive gradients.

    Args:
        reconstruction: the weighted per-sample reconstruction terms.
        objective: how the candidates' terms are weighted (:class:`ExpectedLoss`, :class:`AssignedLoss`, ...).
        uniform_weight: weight of the candidate-balance prior (<= 0: left out); uniform_reduction: its reduction.
        spacing_weight: weight of the candidates' spacing term (<= 0: left out, the paper); spacing_angle: the
            angle in degrees from which a pair of candidates adds nothing to it.
    """

    def __init__(
        self,
        reconstruction: ReconstructionLoss,
        objective: PoseObjective,
        uniform_weight: float,
        uniform_reduction: str = "sum",
        spacing_weight: float = 0.0,
        spacing_angle: float = 30.0,
    ) -> None:
        super().__init__()
        self.reconstruction, self.objective = reconstruction, objective
        self.uniform_weight, self.uniform_reduction = uniform_weight, uniform_reduction
        self.spacing_weight, self.spacing_angle = spacing_weight, spacing_angle

    def forward(self, model: Unicorn, images: torch.Tensor, average_texture: bool = False) -> StepLosses:
        """The step's losses on images (B, 3, S, S) in [0, 1].

        Args:
            average_texture: replace every texture by its mean colour (drawn once per batch by the trainer).

        Returns:
            weighted scalars ``total``, ``rgb``, ``perceptual`` (if enabled), the objective's terms, ``uniform``
            and ``spacing`` (if enabled; they sum to ``total``); ``.probs``: the candidate probabilities (K, B),
            detached.
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
            verts = p.verts
        poses = model.pose(feats["pose"])
        K = poses.probs.shape[0]
        R, T = poses.flat()
        bkg = None if p.background is None else p.background.repeat(K, 1, 1, 1)
        rec, _ = model.render(verts.repeat(K, 1, 1), p.texture.repeat(K, 1, 1, 1), R, T, bkg)
        terms = self.reconstruction(rec, images.repeat(K, 1, 1, 1))
        out = self.objective(poses.probs, poses.log_probs, terms)
        if self.uniform_weight > 0:
            out["uniform"] = self.uniform_weight * uniform_pose_prior(poses.probs, self.uniform_reduction)
        if self.spacing_weight > 0:
            out["spacing"] = self.spacing_weight * candidate_spacing_loss(poses.R, self.spacing_angle)
        return StepLosses(with_total(out, images), poses.probs.detach())
