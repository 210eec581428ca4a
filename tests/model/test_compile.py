"""torch.compile of the networks: the same predictions and parameter names, or eager networks and a warning."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import tiny_config
from unicorn.model import Unicorn
from unicorn.model import compile as compile_module
from unicorn.model.compile import CompileWarning, compile_networks, networks


def test_the_networks_are_every_learned_module():
    model = Unicorn(tiny_config())
    names = [name for name, _ in networks(model)]
    assert names == ["encoders.0", "shape", "texture", "background", "pose", "scale"]
    learned = {id(p) for p in model.parameters()}
    assert learned == {id(p) for _, module in networks(model) for p in module.parameters()}


def test_a_compiled_head_predicts_what_the_eager_one_does_under_the_same_names():
    torch.manual_seed(0)
    model = Unicorn(tiny_config()).eval()
    features = torch.randn(3, model.encoders[0].out_features)
    with torch.no_grad():
        expected = model.pose(features)
    names = list(model.state_dict())
    if not compile_networks(model):
        pytest.skip("torch.compile cannot run on this machine (the warning says why)")
    with torch.no_grad():
        got = model.pose(features)  # compiles the pose head only: the other networks are not called
    assert torch.allclose(got.R, expected.R, atol=1e-5) and torch.allclose(got.probs, expected.probs, atol=1e-5)
    assert list(model.state_dict()) == names  # checkpoints keep their keys


def test_without_a_working_compiler_the_networks_stay_eager_and_a_warning_says_why(monkeypatch):
    monkeypatch.setattr(compile_module, "compile_unavailable", lambda device: "InvalidCxxCompiler: no working C++")
    compiled = []
    monkeypatch.setattr(torch.nn.Module, "compile", lambda self, **kwargs: compiled.append(self))
    model = Unicorn(tiny_config())
    with pytest.warns(CompileWarning, match="InvalidCxxCompiler: no working C\\+\\+.*run eagerly"):
        assert compile_networks(model) is False
    assert compiled == []
    with pytest.raises(ValueError, match="compile mode must be one of"):
        compile_networks(model, "fastest")
