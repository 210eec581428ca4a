"""Pose objectives: how the pose step turns the candidates' reconstruction terms into its loss, chosen by name
(``loss.pose_objective``):

- ``"expected"`` (:class:`ExpectedLoss`, the paper's): ``mean_b sum_k p[k, b] * L_rec(k, b)``;
- ``"assigned"`` (:class:`AssignedLoss`): the same sum with ``p`` detached, and the probabilities learn which
  candidate reconstructs best from ``assignment_weight * candidate_assignment_loss`` (term ``assignment``);
- ``"assigned_best"`` (:class:`AssignedBestLoss`): as ``"assigned"``, with only the best-reconstructing
  candidate's pose refined (weight 1 for it, 0 for the others).

New objectives register with :func:`register_pose_objective`; the model configuration's check accepts every
registered name. The pose step itself is :class:`unicorn.objectives.PoseStep`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch

from unicorn.model.losses import candidate_assignment_loss
from unicorn.registry import Registry

__all__ = [
    "AssignedBestLoss",
    "AssignedLoss",
    "ExpectedLoss",
    "PoseObjective",
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
