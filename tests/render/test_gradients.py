"""Gradients of every backend against finite differences (float64)."""

import pytest
import torch

from unicorn.geometry.mesh import icosphere, spherical_face_uvs
from unicorn.geometry.rotations import look_at_view_transform
from unicorn.render import TexturesUV, TexturesVertex, build_renderer, get_renderer_class, list_renderers

BUILTIN = ["hard", "layered", "softras"]


def _scene(dtype=torch.float64):
    v, f = icosphere(1, dtype=dtype)
    verts = (v * torch.tensor([0.7, 0.5, 0.45], dtype=dtype))[None]
    R, T = look_at_view_transform(2.5, 20.0, 30.0)
    return verts, f, R.to(dtype), T.to(dtype)


def _options(name):
    # larger sigma than training so that a 12-pixel image has several soft pixels per edge
    return {
        "layered": {"sigma": 3e-3},
        "softras": {"sigma": 3e-3, "gamma": 1e-2},
        "hard": {"supersample": 2},
    }.get(name, {})


@pytest.mark.parametrize("name", ["layered", "softras"])
def test_position_gradients_match_finite_differences(name):
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=12, **_options(name))
    colors = torch.rand(1, verts.shape[1], 3, dtype=torch.float64)
    weights = torch.rand(1, 4, 12, 12, dtype=torch.float64)

    def fn(v):
        return (renderer(v, faces, TexturesVertex(colors), R=R, T=T) * weights).sum()

    v = verts.clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (v,), eps=1e-7, atol=1e-5, rtol=1e-3)
    fn(v).backward()
    assert v.grad.abs().sum() > 1e-2  # the check above compared a real, non-zero gradient


@pytest.mark.parametrize("name", BUILTIN)
def test_color_and_background_gradients_match_finite_differences(name):
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=10, **_options(name))
    colors = torch.rand(1, verts.shape[1], 3, dtype=torch.float64, requires_grad=True)
    bg = torch.rand(1, 3, 10, 10, dtype=torch.float64, requires_grad=True)

    def fn(c, b):
        return renderer(verts, faces, TexturesVertex(c), R=R, T=T, background=b)

    assert torch.autograd.gradcheck(fn, (colors, bg), eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("name", BUILTIN)
def test_texture_gradients_match_finite_differences(name):
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=10, **_options(name))
    uvs = spherical_face_uvs(verts[0], faces)
    maps = torch.rand(1, 3, 6, 8, dtype=torch.float64, requires_grad=True)

    def fn(m):
        return renderer(verts, faces, TexturesUV(m, uvs), R=R, T=T)

    assert torch.autograd.gradcheck(fn, (maps,), eps=1e-6, atol=1e-6, fast_mode=True)


def test_hard_renderer_declares_no_position_gradients():
    assert not get_renderer_class("hard").position_gradients
    assert all(get_renderer_class(n).position_gradients for n in ("layered", "softras"))
    assert set(BUILTIN) <= set(list_renderers())
