"""The objectives of a model configuration: the loss modules their steps share."""

from __future__ import annotations

import dataclasses

import pytest

from tests.support.model import tiny_config
from unicorn.model import Unicorn
from unicorn.model.config import LossConfig, ModelConfigError
from unicorn.objectives import Objectives, build_losses


def test_the_objectives_compile_the_reconstruction_loss_every_step_shares():
    model = Unicorn(tiny_config())
    objectives = Objectives.from_config(model.config["loss"], model)
    named = dict(objectives.networks())
    assert list(named) == ["reconstruction"]
    shared = named["reconstruction"]
    assert objectives.steps["3d"].reconstruction is shared
    assert objectives.steps["3d"].neighbors.reconstruction is shared


def _settings(objectives: Objectives) -> dict:
    """What a loss group sets in the objectives, read from their modules."""
    pose, shape = objectives.steps["pose"], objectives.steps["3d"]
    memory = objectives.memory
    return {
        "rgb": pose.reconstruction.rgb_weight,
        "perceptual": (type(pose.reconstruction.perceptual), pose.reconstruction.perceptual_weight),
        "regularizer": (shape.regularizer.normal_weight, shape.regularizer.laplacian_weight),
        "uniform": (pose.uniform_weight, pose.uniform_reduction),
        "spacing": (pose.spacing_weight, pose.spacing_angle),
        "flip": pose.flip_weight,
        "equivariance": (pose.equivariance_weight, pose.equivariance_roll, pose.equivariance_shift),
        "objective": type(pose.objective),
        "viewpoint": pose.viewpoint,
        "neighbors": (shape.neighbors.weight, memory.size, memory.n_bins, memory.min_angle),
    }


def test_a_loss_group_given_in_part_takes_the_defaults_for_the_rest():
    model = Unicorn(tiny_config())
    part = {"perceptual": "structural", "rgb_weight": 2.0, "memory_size": 64}
    objectives = Objectives.from_config(part, model)
    # the oracle: the whole group written out, LossConfig's defaults with the given keys over them
    whole = Objectives.from_config({**dataclasses.asdict(LossConfig()), **part}, model)
    assert _settings(objectives) == _settings(whole)
    assert objectives.steps["pose"].reconstruction.rgb_weight == 2.0 and objectives.memory.size == 64
    assert objectives.steps["3d"].regularizer.normal_weight == LossConfig().normal_weight


@pytest.mark.parametrize(
    ("loss", "error", "message"),
    [
        (
            {"perceptual": "structural", "rgb_wieght": 2.0},
            KeyError,
            r"unknown key 'rgb_wieght' in model config group 'loss'",
        ),
        ({"perceptual": "structural", "memory_size": 0}, ModelConfigError, r"loss\.memory_size"),
    ],
)
def test_a_loss_group_with_a_bad_key_or_value_fails_naming_it(loss, error, message):
    model = Unicorn(tiny_config())
    with pytest.raises(error, match=message):
        Objectives.from_config(loss, model)
    with pytest.raises(error, match=message):
        build_losses(loss, model.template)
