"""The loss modules of a ``loss`` group, built in one place: the training objectives and refinement use them.

The group's settings that name a registered loss (perceptual loss, pose objective, viewpoint supervision) are
checked here, against the registries of this floor (:func:`check_loss_choices`); the group's ranges and other
values are checked with the model's configuration (:func:`unicorn.model.config.check_model_config`). A group given
in part takes :class:`unicorn.model.config.LossConfig`'s defaults for the keys it leaves out (:func:`loss_group`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

from unicorn.model.config import ModelConfigError, merge_config
from unicorn.model.template import TemplateMesh
from unicorn.objectives.losses import MeshRegularizer, ReconstructionLoss
from unicorn.objectives.perceptual import list_perceptual_losses
from unicorn.objectives.pose_objectives import list_pose_objectives
from unicorn.objectives.viewpoint import list_viewpoint_supervisions
from unicorn.registry import PLUGINS_ENV

__all__ = ["LOSS_CHOICES", "ImageLosses", "build_losses", "check_loss_choices", "loss_group"]

#: the ``loss`` settings that name a registered loss: ``loss.key`` -> a function listing the allowed values (the
#: registry's names, registered ones included; None where the loss may be left out)
LOSS_CHOICES: dict[str, Callable[[], tuple[Any, ...]]] = {
    "loss.perceptual": lambda: (*list_perceptual_losses(), None),
    "loss.pose_objective": lambda: tuple(list_pose_objectives()),
    "loss.viewpoint": lambda: (*list_viewpoint_supervisions(), None),
}


def check_loss_choices(loss: Mapping[str, Any], prefix: str = "") -> None:
    """Check that each setting of :data:`LOSS_CHOICES` names a registered loss.

    Raises:
        ModelConfigError: the first unknown name, with its key (``prefix`` + ``loss.key``) and the allowed values.
    """
    for key, names in LOSS_CHOICES.items():
        value = loss[key.split(".")[1]]
        if value not in (allowed := names()):
            raise ModelConfigError(
                f"{prefix}{key} must be one of {allowed}, got {value!r} (one a plugin registers needs that plugin "
                f"imported: {PLUGINS_ENV}=module)"
            )


def loss_group(loss: Mapping[str, Any]) -> dict[str, Any]:
    """The whole ``loss`` group that ``loss`` describes: the keys it leaves out at
    :class:`unicorn.model.config.LossConfig`'s defaults (``{"perceptual": "structural"}`` reads as
    ``Unicorn(loss={"perceptual": "structural"})`` does), its values range-checked.

    Raises:
        KeyError: a key the group does not have (a misspelt one), named with the known keys.
        ModelConfigError: a value out of its range or not among the allowed ones, named with its key.
    """
    return merge_config(loss=loss)["loss"]


class ImageLosses(NamedTuple):
    """The per-image loss modules of the 3D step: ``reconstruction`` (RGB and perceptual terms of a render against
    its image) and ``regularizer`` (the mesh's normal consistency and Laplacian terms)."""

    reconstruction: ReconstructionLoss
    regularizer: MeshRegularizer


def build_losses(loss: Mapping[str, Any], template: TemplateMesh) -> ImageLosses:
    """The loss modules a ``loss`` group (a model configuration's, or a part of one: :func:`loss_group`) describes
    for meshes of ``template``'s faces: the perceptual loss chosen by name, weights <= 0 leaving their terms out.

    Raises:
        KeyError: a key the group does not have.
        ModelConfigError: a value out of its range, or a setting naming no registered loss
            (:func:`check_loss_choices`).
    """
    loss = loss_group(loss)
    check_loss_choices(loss)
    reconstruction = ReconstructionLoss.from_config(loss)
    regularizer = MeshRegularizer.from_config(loss, template.faces, template.num_verts)
    return ImageLosses(reconstruction, regularizer)
