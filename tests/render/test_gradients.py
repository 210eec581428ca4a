"""Gradients of every backend against finite differences (float64)."""

import pytest
import torch

from unicorn.geometry.mesh import icosphere, spherical_face_uvs
from unicorn.geometry.rotations import look_at_view_transform
from unicorn.render import TexturesUV, TexturesVertex, build_renderer, list_renderers


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


@pytest.mark.parametrize("name", list_renderers())
def test_color_and_background_gradients_match_finite_differences(name):
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=10, **_options(name))
    colors = torch.rand(1, verts.shape[1], 3, dtype=torch.float64, requires_grad=True)
    bg = torch.rand(1, 3, 10, 10, dtype=torch.float64, requires_grad=True)

    def fn(c, b):
        return renderer(verts, faces, TexturesVertex(c), R=R, T=T, background=b)

    assert torch.autograd.gradcheck(fn, (colors, bg), eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("name", list_renderers())
def test_texture_gradients_match_finite_differences(name):
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=10, **_options(name))
    uvs = spherical_face_uvs(verts[0], faces)
    maps = torch.rand(1, 3, 6, 8, dtype=torch.float64, requires_grad=True)

    def fn(m):
        return renderer(verts, faces, TexturesUV(m, uvs), R=R, T=T)

    assert torch.autograd.gradcheck(fn, (maps,), eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("name", list_renderers())
def test_position_gradients_says_whether_silhouettes_follow_the_vertices(name):
    # the flag a caller reads (a pose must be fitted by silhouettes) against what autograd gives the alpha channel:
    # the hard backend's colours still depend on the vertices through the barycentrics, its coverage does not
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=12, **_options(name))
    v = verts.clone().requires_grad_()
    white = TexturesVertex(torch.ones(1, verts.shape[1], 3, dtype=torch.float64))
    alpha = renderer(v, faces, white, R=R, T=T)[:, 3]
    assert alpha.sum() > 10  # the mesh is in view
    weights = torch.rand(alpha.shape, generator=torch.Generator().manual_seed(0), dtype=alpha.dtype)
    (grad,) = torch.autograd.grad((alpha * weights).sum(), v, allow_unused=True)
    moves = grad is not None and grad.abs().sum() > 1e-6
    assert moves == renderer.position_gradients


@pytest.mark.parametrize("name", list_renderers())
def test_depth_gradients_match_finite_differences(name):
    # RenderOutput.depth, like PyTorch3D's zbuf, is a function of the vertices a depth loss can fit
    verts, faces, R, T = _scene()
    renderer = build_renderer(name, image_size=12, **_options(name))
    white = TexturesVertex(torch.ones(1, verts.shape[1], 3, dtype=torch.float64))
    weights = torch.rand(1, 1, *renderer.raster_size, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def fn(v):
        return (renderer.render(v, faces, white, R=R, T=T).depth * weights).sum()

    v = verts.clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (v,), eps=1e-7, atol=1e-5, rtol=1e-3)
    fn(v).backward()
    assert v.grad.abs().sum() > 1e-2  # the check above compared a real, non-zero gradient
