"""Pose objectives: how the pose step turns the candidates' reconstruction terms into its loss, chosen by name
(``loss.pose_objective``):

- ``"expected"`` (:class:`ExpectedLoss`, the paper's): ``mean_b sum_k p[k, b] * L_rec(k, b)``;
- ``"assigned"`` (:class:`AssignedLoss`): the same sum with ``p`` detached, and the probabilities learn which
  candidate reconstructs best from ``assignment_weight * candidate_assignment_loss`` (term ``assignment``);
- ``"assigned_best"`` (:class:`AssignedBestLoss`): as ``"assigned"``, with only the best-reconstructing
  candidate's pose refined (weight 1 for it, 0 for the others).

- ``"sampled"`` (:class:`SampledCandidates`, MagicPony's schedule): one candidate rendered per image in both
  steps, its score regressing its loss.

An objective also says which candidates each step renders (:meth:`PoseObjective.pose_terms`,
:meth:`PoseObjective.shape_pose`); :class:`AllCandidates` is the default of the first three: every candidate in
the pose step, the most likely one in the 3D step. New objectives register with :func:`register_pose_objective`;
the model configuration's check accepts every registered name. The steps themselves are
:class:`unicorn.objectives.PoseStep` and :class:`unicorn.objectives.ShapeStep`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch

from unicorn.model.config import LOSS_KEYS
from unicorn.model.pose import PoseOutput
from unicorn.objectives.losses import candidate_assignment_loss
from unicorn.registry import Registry

__all__ = [
    "AllCandidates",
    "AssignedBestLoss",
    "AssignedLoss",
    "ExpectedLoss",
    "PoseObjective",
    "Reconstruct",
    "SampledCandidates",
    "build_pose_objective",
    "list_pose_objectives",
    "register_pose_objective",
]


#: renders the pose step's detached prediction at n poses per image, R (n * B, 3, 3) and T (n * B, 3) pose-major,
#: and returns its reconstruction terms, name -> (n * B,)
Reconstruct = Callable[[torch.Tensor, torch.Tensor, int], dict[str, torch.Tensor]]


class PoseObjective(Protocol):
    """Which pose candidates the two steps render, and how the pose step weights their reconstruction terms."""

    def pose_terms(self, poses: PoseOutput, reconstruct: Reconstruct, iteration: int | None) -> dict[str, torch.Tensor]:
        """The pose step's scalar terms for the candidates ``poses`` (with gradients), rendering the candidates it
        chooses with ``reconstruct``."""
        ...

    def shape_pose(
        self, poses: PoseOutput, iteration: int | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The 3D step's pose R (B, 3, 3), T (B, 3) from detached candidates, and each image's weight (B,) of its
        terms, or None (weight 1)."""
        ...


class AllCandidates:
    """Every candidate rendered in the pose step, its terms weighted by :meth:`__call__`; the most likely one in
    the 3D step."""

    def __call__(
        self, probs: torch.Tensor, log_probs: torch.Tensor, terms: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Scalar terms from the probabilities ``probs`` and ``log_probs`` (K, B) and the candidates' terms
        (name -> (K * B,), candidate-major)."""
        raise NotImplementedError

    def pose_terms(self, poses: PoseOutput, reconstruct: Reconstruct, iteration: int | None) -> dict[str, torch.Tensor]:
        R, T = poses.flat()
        return self(poses.probs, poses.log_probs, reconstruct(R, T, poses.probs.shape[0]))

    def shape_pose(
        self, poses: PoseOutput, iteration: int | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        R, T = poses.select()
        return R, T, None


_POSE_OBJECTIVES: Registry[PoseObjective] = Registry(
    "pose objective", key="pose_objective", methods=("pose_terms", "shape_pose")
)


def register_pose_objective(name: str, *, overwrite: bool = False) -> Callable[[type], type]:
    """Class decorator: make a pose objective available as ``loss.pose_objective=name``; its constructor receives
    the options of the ``loss`` group it names (e.g. ``assignment_weight``)."""
    return _POSE_OBJECTIVES.register(name, overwrite=overwrite)


def list_pose_objectives() -> list[str]:
    """The registered pose-objective names, sorted."""
    return _POSE_OBJECTIVES.names()


def build_pose_objective(name: str, **options: Any) -> PoseObjective:
    """The pose objective registered as ``name``, built from the options its constructor names; the other keys of
    the ``loss`` group (:data:`~unicorn.model.config.LOSS_KEYS`) are left out.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones listed).
        unicorn.registry.UnknownOptionError: an option that is neither the constructor's nor a ``loss`` key.
    """
    return _POSE_OBJECTIVES.build(name, options, group_keys=LOSS_KEYS)


def _weighted(weights: torch.Tensor, terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``mean_b sum_k weights[k, b] * term[k, b]`` of every term (K * B,)."""
    K, B = weights.shape
    return {name: (weights * value.view(K, B)).sum(0).mean() for name, value in terms.items()}


@register_pose_objective("expected")
class ExpectedLoss(AllCandidates):
    """The paper's expected reconstruction loss: gradients reach the probabilities through ``p``."""

    def __call__(
        self, probs: torch.Tensor, log_probs: torch.Tensor, terms: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        return _weighted(probs, terms)


@register_pose_objective("assigned")
class AssignedLoss(AllCandidates):
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


@register_pose_objective("sampled")
class SampledCandidates:
    """MagicPony's candidate schedule: one candidate rendered per image, its score regressing its loss.

    Each step renders one candidate per image (:meth:`pick`): a uniformly random one until ``sample_random_until``;
    from then on the most likely one for all but a share of the images that falls linearly from 1 to
    ``sample_random_share`` over ``sample_ramp`` iterations and stays there, a random one for that share. Until
    ``sample_uniform_until`` the probabilities are uniform. The probability head's outputs are negative scores:
    ``p = softmax(logits / tau)`` with the temperature ``tau = 1 / clip(iteration / sample_tau_period, 1, 100)``,
    and in the pose step the rendered candidate's ``-logit`` regresses its detached loss (term ``score``, weight
    ``score_weight``). The rendered candidate's terms are weighted by ``min(1, K * p)`` (detached), so an unlikely
    random candidate moves the pose and the 3D branches little (:meth:`weights`).

    Args:
        score_weight: weight of the score regression.
        sample_random_until, sample_ramp, sample_random_share, sample_uniform_until, sample_tau_period: the schedule
            (iterations, and the random share in [0, 1]).
    """

    def __init__(
        self,
        score_weight: float = 0.1,
        sample_random_until: int = 800,
        sample_ramp: int = 400,
        sample_random_share: float = 0.2,
        sample_uniform_until: int = 400,
        sample_tau_period: int = 200,
    ) -> None:
        if not 0.0 <= sample_random_share <= 1.0 or min(sample_random_until, sample_ramp, sample_uniform_until) < 0:
            raise ValueError(
                "sample_random_share must be in [0, 1] and the schedule's iterations >= 0, got "
                f"{sample_random_share}, {sample_random_until}, {sample_ramp}, {sample_uniform_until}"
            )
        if sample_tau_period < 1:
            raise ValueError(f"sample_tau_period must be >= 1, got {sample_tau_period}")
        self.score_weight = float(score_weight)
        self.random_until, self.ramp = int(sample_random_until), int(sample_ramp)
        self.final_share, self.uniform_until = float(sample_random_share), int(sample_uniform_until)
        self.tau_period = int(sample_tau_period)

    def random_share(self, iteration: int | None) -> float:
        """The share of images rendered with a random candidate at ``iteration`` (None: the final share)."""
        if iteration is None:
            return self.final_share
        if iteration < self.random_until:
            return 1.0
        t = 1.0 if self.ramp == 0 else min(1.0, (iteration - self.random_until) / self.ramp)
        return 1.0 - t * (1.0 - self.final_share)

    def temperature(self, iteration: int | None) -> float:
        """``tau = 1 / clip(iteration / sample_tau_period, 1, 100)`` (None: the final 0.01)."""
        if iteration is None:
            return 0.01
        return 1.0 / min(max(iteration / self.tau_period, 1.0), 100.0)

    def probabilities(self, logits: torch.Tensor, iteration: int | None) -> torch.Tensor:
        """(K, B) probabilities at ``iteration`` from the head's logits (K, B): uniform until
        ``sample_uniform_until``, ``softmax(logits / tau)`` after."""
        if iteration is not None and iteration < self.uniform_until:
            return torch.full_like(logits, 1.0 / logits.shape[0])
        return torch.softmax(logits / self.temperature(iteration), dim=0)

    def pick(self, logits: torch.Tensor, iteration: int | None) -> torch.Tensor:
        """(B,) the candidate rendered for each image, from the head's logits (K, B) (torch's global generator)."""
        K, B = logits.shape
        random = torch.randint(K, (B,), device=logits.device)
        if iteration is not None and iteration < self.uniform_until:
            return random
        explore = torch.rand(B, device=logits.device) < self.random_share(iteration)
        return torch.where(explore, random, logits.argmax(0))

    def weights(self, logits: torch.Tensor, picked: torch.Tensor, iteration: int | None) -> torch.Tensor:
        """(B,) detached weights ``min(1, K * p[picked])`` of the rendered candidates' terms."""
        p = self.probabilities(logits.detach(), iteration)
        b = torch.arange(picked.shape[0], device=picked.device)
        return (p.shape[0] * p[picked, b]).clamp(max=1.0)

    def __call__(
        self,
        logits: torch.Tensor,
        picked: torch.Tensor,
        terms: dict[str, torch.Tensor],
        iteration: int | None = None,
    ) -> dict[str, torch.Tensor]:
        """The pose step's terms for the rendered candidates ``picked`` (B,): each term (B,) weighted by
        :meth:`weights` and averaged, and ``score``: the mean squared error of ``-logits[picked]`` against the
        summed terms (detached)."""
        w = self.weights(logits, picked, iteration)
        out = {name: (w * value).mean() for name, value in terms.items()}
        b = torch.arange(picked.shape[0], device=picked.device)
        loss = torch.stack(list(terms.values())).sum(0).detach()
        out["score"] = self.score_weight * (-logits[picked, b] - loss).square().mean()
        return out

    def pose_terms(self, poses: PoseOutput, reconstruct: Reconstruct, iteration: int | None) -> dict[str, torch.Tensor]:
        """The picked candidate of each image rendered (:meth:`pick`), its terms as :meth:`__call__` weights them."""
        if poses.logits is None:
            raise ValueError("the sampled pose objective needs the probability head's logits")
        picked = self.pick(poses.logits.detach(), iteration)
        R, T = poses.select(picked)
        return self(poses.logits, picked, reconstruct(R, T, 1), iteration)

    def shape_pose(
        self, poses: PoseOutput, iteration: int | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The picked candidate of each image (a fresh draw), weighted by :meth:`weights`."""
        if poses.logits is None:  # one candidate: nothing to pick
            R, T = poses.select()
            return R, T, None
        picked = self.pick(poses.logits, iteration)
        R, T = poses.select(picked)
        return R, T, self.weights(poses.logits, picked, iteration)
