"""The training objectives of a model configuration, by step kind, and the training state they hold."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import nn

from unicorn.model import Unicorn
from unicorn.model.compile import networks
from unicorn.objectives.loss_factory import build_losses, loss_group
from unicorn.objectives.neighbors import NeighborLoss, NeighborMemory
from unicorn.objectives.pose_objectives import build_pose_objective
from unicorn.objectives.pose_step import PoseStep
from unicorn.objectives.shape_step import ShapeStep
from unicorn.objectives.step_losses import StepLosses
from unicorn.objectives.viewpoint import build_viewpoint_supervision

__all__ = ["Objectives", "training_networks"]


class Objectives(nn.Module):
    """The pose step and the 3D step (``self.steps["pose"]``, ``self.steps["3d"]``), sharing their loss modules.

    Args:
        pose: the pose step; shape: the 3D step.

    Example:
        >>> model = Unicorn(image_size=32, loss={"perceptual": "structural"})  # no VGG16 weights to fetch
        >>> objectives = Objectives.from_config(model.config["loss"], model)
        >>> losses = objectives("pose", model, torch.rand(2, 3, 32, 32))
        >>> sorted(losses)
        ['perceptual', 'rgb', 'total', 'uniform']
    """

    def __init__(self, pose: PoseStep, shape: ShapeStep) -> None:
        super().__init__()
        self.steps = nn.ModuleDict({"pose": pose, "3d": shape})

    @classmethod
    def from_config(cls, loss: Mapping[str, Any], model: Unicorn) -> Objectives:
        """The objectives a ``loss`` group describes (:class:`unicorn.model.config.LossConfig`) for ``model``'s
        template: the loss modules of :func:`unicorn.objectives.loss_factory.build_losses`, the pose objective and
        the viewpoint supervision chosen by name, weights <= 0 leaving their terms out. Keys ``loss`` leaves out
        take LossConfig's defaults (:func:`unicorn.objectives.loss_factory.loss_group`).

        Raises:
            KeyError: a key the group does not have.
            ModelConfigError: a value out of its range, or a name of no registered loss.
        """
        loss = loss_group(loss)
        reconstruction, regularizer = build_losses(loss, model.template)
        objective = build_pose_objective(loss["pose_objective"], **loss)
        pose = PoseStep(
            reconstruction,
            objective,
            loss["uniform_weight"],
            loss["uniform_reduction"],
            loss["spacing_weight"],
            loss["spacing_angle"],
            None if loss["viewpoint"] is None else build_viewpoint_supervision(loss["viewpoint"], **loss),
            loss["flip_weight"],
            loss["equivariance_weight"],
            loss["equivariance_roll"],
            loss["equivariance_shift"],
        )
        memory = NeighborMemory(loss["memory_size"], loss["n_bins"], loss["min_angle"])
        neighbors = NeighborLoss(reconstruction, memory, loss["neighbor_weight"])
        shape = ShapeStep(reconstruction, regularizer, neighbors, objective)
        return cls(pose, shape)

    def networks(self) -> Iterator[tuple[str, nn.Module]]:
        """The loss modules worth compiling with the model's networks (``model.compile``): the reconstruction loss
        that every step and the neighbour term share (the pixel MSE and the perceptual network; the renderer and the
        regularisers stay eager)."""
        yield "reconstruction", self.steps["pose"].reconstruction

    @property
    def memory(self) -> NeighborMemory:
        """The neighbour memory bank (training state: a trainer saves it with its checkpoints)."""
        neighbors = self.steps["3d"].neighbors
        assert neighbors is not None
        return neighbors.memory

    def forward(
        self,
        kind: str,
        model: Unicorn,
        images: torch.Tensor,
        average_texture: bool | torch.Tensor = False,
        iteration: int | None = None,
    ) -> StepLosses:
        """The losses of a ``"pose"`` or ``"3d"`` step on images (B, 3, S, S) in [0, 1] at training ``iteration``."""
        return self.steps[kind](model, images, average_texture=average_texture, iteration=iteration)

    def pose_step(self, model: Unicorn, images: torch.Tensor, average_texture: bool = False) -> StepLosses:
        """The pose step's losses (:class:`PoseStep`)."""
        return self("pose", model, images, average_texture)

    def step_3d(self, model: Unicorn, images: torch.Tensor, average_texture: bool = False) -> StepLosses:
        """The 3D step's losses (:class:`ShapeStep`)."""
        return self("3d", model, images, average_texture)


def training_networks(model: Unicorn, objectives: Objectives) -> list[tuple[str, nn.Module]]:
    """What ``model.compile`` compiles, by name: the model's networks (:func:`unicorn.model.compile.networks`), then
    the objectives' (:meth:`Objectives.networks`)."""
    return [*networks(model), *objectives.networks()]
