"""UNICORN's training objectives, owned by the trainer (:class:`unicorn.lit.UnicornLitModule`).

The model (:class:`unicorn.model.Unicorn`) predicts and renders; the objectives take it and a batch and return
weighted loss terms with the batch's pose probabilities (:class:`StepLosses`). Each step detaches what the paper
says, so only its own branches receive gradients.

- :class:`Objectives`: the two steps built from a model configuration's ``loss`` group, by step kind
  (``"pose"``, ``"3d"``), and the training state they hold (the neighbour memory).
- ``pose_step``: :class:`PoseStep` and the pose objectives chosen by name (``loss.pose_objective``:
  :class:`ExpectedLoss`, :class:`AssignedLoss`, :class:`AssignedBestLoss`; :func:`register_pose_objective`).
- ``shape_step``: :class:`ShapeStep` (the 3D step).
- ``neighbors``: :class:`NeighborLoss` and its memory bank (:class:`NeighborMemory`).

The loss functions themselves (reconstruction, perceptual, mesh regularisers) are :mod:`unicorn.model.losses`'
and :mod:`unicorn.model.perceptual`'s, shared with test-time refinement.
"""

from unicorn.model.pose_objectives import (
    AssignedBestLoss,
    AssignedLoss,
    ExpectedLoss,
    PoseObjective,
    build_pose_objective,
    list_pose_objectives,
    register_pose_objective,
)
from unicorn.objectives.neighbors import NeighborLoss, NeighborMatch, NeighborMemory
from unicorn.objectives.objectives import Objectives
from unicorn.objectives.pose_step import PoseStep
from unicorn.objectives.shape_step import ShapeStep
from unicorn.objectives.step_losses import StepLosses

__all__ = [
    "AssignedBestLoss",
    "AssignedLoss",
    "ExpectedLoss",
    "NeighborLoss",
    "NeighborMatch",
    "NeighborMemory",
    "Objectives",
    "PoseObjective",
    "PoseStep",
    "ShapeStep",
    "StepLosses",
    "build_pose_objective",
    "list_pose_objectives",
    "register_pose_objective",
]
