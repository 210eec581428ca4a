"""The loss modules of a ``loss`` group built in one place, and the loss names checked against the registries."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import tiny_config
from unicorn.config import ConfigError, validate
from unicorn.model import Unicorn, merge_config
from unicorn.objectives import MeshRegularizer, Objectives, ReconstructionLoss, build_losses, pose_objectives
from unicorn.objectives.loss_factory import LOSS_CHOICES, check_loss_choices
from unicorn.objectives.perceptual import StructuralLoss
from unicorn.objectives.pose_objectives import ExpectedLoss

#: every loss setting that names a registered loss, with the values the library ships (docs/training.md), written
#: out here rather than read from the registries the check itself reads
DOCUMENTED_LOSS_CHOICES = {
    "loss.perceptual": ("structural", "vgg", None),
    "loss.pose_objective": ("assigned", "assigned_best", "expected", "sampled"),
    "loss.viewpoint": ("renders", None),
}


def test_the_loss_choices_are_the_documented_ones() -> None:
    assert {key: names() for key, names in LOSS_CHOICES.items()} == DOCUMENTED_LOSS_CHOICES
    defaults = merge_config()["loss"]
    for key, allowed in DOCUMENTED_LOSS_CHOICES.items():
        name = key.split(".")[1]
        assert defaults[name] in allowed, key
        for value in allowed:
            check_loss_choices({**defaults, name: value})


@pytest.mark.parametrize(
    ("loss", "message"),
    [
        ({"perceptual": "lpips"}, r"loss\.perceptual must be one of .*'lpips'"),
        ({"pose_objective": "best"}, r"loss\.pose_objective must be one of"),
        (
            {"viewpoint": "render"},
            r"loss\.viewpoint must be one of \('renders', None\), got 'render' "
            r"\(one a plugin registers needs that plugin imported: UNICORN_PLUGINS=module\)$",
        ),
    ],
)
def test_an_unknown_loss_name_fails_naming_the_key(loss, message) -> None:
    model = Unicorn(tiny_config())
    bad = {**model.config["loss"], **loss}
    with pytest.raises(ValueError, match=message):
        check_loss_choices(bad)
    with pytest.raises(ValueError, match=message):
        Objectives.from_config(bad, model)
    with pytest.raises(ValueError, match=message):
        build_losses(bad, model.template)


def test_the_training_config_check_names_the_training_key() -> None:
    base = {
        "model": {"image_size": 32},
        "dataset": {"img_size": 32, "root": None},
        "renderer": {"name": "layered", "camera": {"fov": 30.0}},
    }
    with pytest.raises(ConfigError, match=r"model\.loss\.pose_objective must be one of"):
        validate({**base, "model": {"image_size": 32, "loss": {"pose_objective": "best"}}})


def test_a_registered_pose_objective_is_allowed(monkeypatch) -> None:
    # an objective registered by the user's code is accepted by the check with no list to update
    loss = {**merge_config()["loss"], "pose_objective": "mine"}
    with pytest.raises(ValueError, match=r"loss\.pose_objective must be one of"):
        check_loss_choices(loss)
    monkeypatch.setitem(pose_objectives._POSE_OBJECTIVES._entries, "mine", ExpectedLoss)
    check_loss_choices(loss)


def test_the_factory_builds_the_3d_step_s_modules() -> None:
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"normal_weight": 0.5, "laplacian_weight": 0.25}))
    losses = build_losses(model.config["loss"], model.template)
    assert isinstance(losses.reconstruction, ReconstructionLoss) and isinstance(losses.regularizer, MeshRegularizer)
    assert isinstance(losses.reconstruction.perceptual, StructuralLoss)
    assert (losses.regularizer.normal_weight, losses.regularizer.laplacian_weight) == (0.5, 0.25)
    step = Objectives.from_config(model.config["loss"], model).steps["3d"]
    assert type(step.reconstruction) is type(losses.reconstruction)
    assert step.regularizer.state_dict().keys() == losses.regularizer.state_dict().keys()
