"""torch.compile of the networks and of other modules (the reconstruction loss): the same results and parameter names,
or eager modules and a warning."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import tiny_config
from unicorn.model import Unicorn
from unicorn.model import compile as compile_module
from unicorn.model.compile import CompileWarning, compile_modules, compile_networks, networks
from unicorn.objectives import Objectives


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


def test_cudagraphs_compiles_with_that_backend_on_cuda_and_not_elsewhere(monkeypatch):
    options = []
    monkeypatch.setattr(torch.nn.Module, "compile", lambda self, **kwargs: options.append(kwargs))
    model = Unicorn(tiny_config())
    with pytest.warns(CompileWarning, match="cudagraphs backend captures CUDA graphs: it needs a CUDA device"):
        assert compile_networks(model, "cudagraphs") is False  # on the CPU: nothing to capture
    assert options == []
    monkeypatch.setattr(compile_module, "compile_unavailable", lambda device, mode="default": None)
    assert compile_networks(model, "cudagraphs", device="cuda")
    assert options and all(kwargs == {"backend": "cudagraphs"} for kwargs in options)


def test_without_a_working_compiler_the_networks_stay_eager_and_a_warning_says_why(monkeypatch):
    monkeypatch.setattr(
        compile_module, "compile_unavailable", lambda device, mode="default": "InvalidCxxCompiler: no working C++"
    )
    compiled = []
    monkeypatch.setattr(torch.nn.Module, "compile", lambda self, **kwargs: compiled.append(self))
    model = Unicorn(tiny_config())
    with pytest.warns(CompileWarning, match="InvalidCxxCompiler: no working C\\+\\+.*run eagerly"):
        assert compile_networks(model) is False
    assert compiled == []
    with pytest.raises(ValueError, match="compile mode must be one of"):
        compile_networks(model, "fastest")


def test_a_compiled_reconstruction_loss_gives_the_eager_terms_and_gradients():
    torch.manual_seed(0)
    model = Unicorn(tiny_config())  # the structural perceptual term: multi-scale SSIM and Sobel gradients
    loss = Objectives.from_config(model.config["loss"], model).steps["pose"].reconstruction
    target = torch.rand(4, 3, 32, 32)
    rec = torch.rand(4, 3, 32, 32, requires_grad=True)
    expected = loss(rec, target)
    (expected_grad,) = torch.autograd.grad(sum(t.sum() for t in expected.values()), rec)
    if not compile_modules([loss]):
        pytest.skip("torch.compile cannot run on this machine (the warning says why)")
    got = loss(rec, target)
    (grad,) = torch.autograd.grad(sum(t.sum() for t in got.values()), rec)
    assert sorted(got) == sorted(expected) == ["perceptual", "rgb"]
    for name in got:
        torch.testing.assert_close(got[name], expected[name], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(grad, expected_grad, atol=1e-6, rtol=1e-4)


def test_a_compiled_texture_generator_trains_as_the_eager_one():
    """Forward and backward through the upsampling decoder from its 1 x 1 start, where the CPU backend once failed
    to generate the backward of the interpolations (pytorch/pytorch#160391)."""
    torch.manual_seed(0)
    generator = Unicorn(tiny_config()).texture.generator
    codes = torch.randn(4, generator.code_dim, requires_grad=True)
    expected = generator(codes)
    (expected_grad,) = torch.autograd.grad(expected.square().sum(), codes)
    if not compile_modules([generator]):
        pytest.skip("torch.compile cannot run on this machine (the warning says why)")
    got = generator(codes)
    (grad,) = torch.autograd.grad(got.square().sum(), codes)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(grad, expected_grad, atol=1e-5, rtol=1e-4)
