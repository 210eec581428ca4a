"""The objectives of a model configuration: the loss modules their steps share."""

from __future__ import annotations

from tests.support.model import tiny_config
from unicorn.model import Unicorn
from unicorn.objectives import Objectives


def test_the_objectives_compile_the_reconstruction_loss_every_step_shares():
    model = Unicorn(tiny_config())
    objectives = Objectives.from_config(model.config["loss"], model)
    named = dict(objectives.networks())
    assert list(named) == ["reconstruction"]
    shared = named["reconstruction"]
    assert objectives.steps["3d"].reconstruction is shared
    assert objectives.steps["3d"].neighbors.reconstruction is shared
