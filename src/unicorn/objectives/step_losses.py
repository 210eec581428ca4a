"""What a training step returns: its weighted loss terms and the batch's pose-candidate probabilities."""

from __future__ import annotations

import torch

__all__ = ["StepLosses", "with_total"]


class StepLosses(dict):
    """A step's weighted loss terms (name -> scalar tensor, summing to ``"total"``), ``probs``, the batch's
    pose-candidate probabilities (K, B), detached, and ``stats``: other detached scalars worth logging (name ->
    scalar tensor, not part of the total)."""

    def __init__(
        self, terms: dict[str, torch.Tensor], probs: torch.Tensor, stats: dict[str, torch.Tensor] | None = None
    ) -> None:
        super().__init__(terms)
        self.probs = probs
        self.stats = dict(stats or {})


def with_total(terms: dict[str, torch.Tensor], like: torch.Tensor) -> dict[str, torch.Tensor]:
    """``terms`` with ``"total"``, their sum, added (a zero scalar on ``like``'s device when there are none)."""
    terms["total"] = torch.stack(list(terms.values())).sum() if terms else like.new_zeros(())
    return terms
