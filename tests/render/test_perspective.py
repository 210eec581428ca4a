"""Perspective-correct barycentrics (``perspective_correct=True``) against a ray-cast oracle, and their gradients.

The scene is a quad seen at a grazing angle: its far corners are five times as deep as its near ones, where the
screen-space (affine) barycentrics of a pixel are far from those of the 3D point the pixel's ray hits.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch

from unicorn.geometry.cameras import PerspectiveCamera, pixel_to_ndc
from unicorn.render import Fragments, TexturesVertex, build_renderer, get_renderer_class, list_renderers

FOV = 30.0


def _correctable() -> list[str]:
    """The registered backends that take the option."""
    return [n for n in list_renderers() if "perspective_correct" in inspect.signature(get_renderer_class(n)).parameters]


def _options(name: str) -> dict:
    # larger sigma than training so that a small image has soft pixels along every edge
    return {"layered": {"sigma": 3e-3}, "softras": {"sigma": 3e-3, "gamma": 1e-2}, "hard": {"supersample": 2}}.get(
        name, {}
    )


def _grazing_quad(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """A quad in view coordinates (1, 4, 3) receding from depth 1.2 to 6 (a floor seen from just above), as two
    triangles (2, 3) whose diagonal runs from a near corner to a far one."""
    verts = torch.tensor(
        [[[0.32, -0.25, 1.2], [-0.30, -0.27, 1.25], [-1.5, -0.22, 6.0], [1.4, -0.2, 5.8]]], dtype=dtype
    )
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return verts, faces


def _ray_cast(
    view_verts: np.ndarray, faces: np.ndarray, fragments: Fragments, focal: float
) -> tuple[np.ndarray, np.ndarray]:
    """For every pair of ``fragments`` whose face contains its pixel centre: the barycentrics (M', 3) and depth
    (M',) of the point where the ray through the pixel centre meets the face's plane (Moeller-Trumbore, float64).
    Written from the camera model alone: view rays ``(x_ndc / f, y_ndc / f, 1)``."""
    H, W = fragments.image_size
    inside = fragments.inside.numpy()
    pix = fragments.pix.numpy()[inside] % (H * W)
    colrow = torch.tensor(np.stack([pix % W, pix // W], -1), dtype=torch.float64)
    ndc = pixel_to_ndc(colrow, (H, W)).numpy()
    dirs = np.concatenate([ndc / focal, np.ones((len(ndc), 1))], -1)  # (M', 3), unit z: t is the view depth
    a, b, c = (view_verts[faces[fragments.face.numpy()[inside], i]] for i in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(dirs, e2)
    det = (e1 * p).sum(-1)
    s = -a  # the rays start at the camera centre (the origin)
    u = (s * p).sum(-1) / det
    q = np.cross(s, e1)
    v = (dirs * q).sum(-1) / det
    t = (e2 * q).sum(-1) / det
    return np.stack([1 - u - v, u, v], -1), t


@pytest.mark.parametrize("name", _correctable())
def test_perspective_correct_barycentrics_match_ray_casting_affine_ones_do_not(name):
    verts, faces = _grazing_quad()
    camera = PerspectiveCamera(fov=FOV)
    colors = TexturesVertex(torch.rand(1, 4, 3, dtype=torch.float64))
    found = {}
    for correct in (True, False):
        renderer = build_renderer(
            name, image_size=32, camera=camera, perspective_correct=correct, **_options(name)
        ).double()
        frags = renderer.render(verts, faces, colors).fragments  # verts in view coordinates: no R, T
        bary, depth = _ray_cast(verts[0].numpy(), faces.numpy(), frags, float(camera.focal_length))
        inside = frags.inside.numpy()
        assert inside.sum() > 100 and (bary > -1e-9).all()  # the oracle's hits lie on the faces too
        found[correct] = (frags.bary.detach().numpy()[inside] - bary, frags.zbuf.detach().numpy()[inside] - depth)
    bary_err, depth_err = found[True]
    assert np.abs(bary_err).max() < 1e-9 and np.abs(depth_err).max() < 1e-9
    affine_bary_err, affine_depth_err = found[False]
    assert np.abs(affine_bary_err).max() > 0.1  # what the option changes: screen-space interpolation is off here
    assert np.abs(affine_depth_err).max() > 0.3


@pytest.mark.parametrize("name", _correctable())
def test_perspective_correct_is_off_by_default(name):
    assert build_renderer(name, image_size=8).rasterizer.perspective_correct is False
    with pytest.raises(ValueError, match="perspective_correct must be True or False, got 'false'"):
        build_renderer(name, image_size=8, perspective_correct="false")


@pytest.mark.parametrize("name", _correctable())
def test_perspective_correct_gradients_match_finite_differences(name):
    verts, faces = _grazing_quad()
    renderer = build_renderer(name, image_size=12, perspective_correct=True, **_options(name))
    g = torch.Generator().manual_seed(0)
    colors = torch.rand(1, 4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    weights = torch.rand(1, 4, 12, 12, generator=g, dtype=torch.float64)

    def fn(v: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return (renderer(v, faces, TexturesVertex(c)) * weights).sum()

    v = verts.clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (v, colors), eps=1e-7, atol=1e-5, rtol=1e-3)
    (grad,) = torch.autograd.grad(fn(v, colors), v)
    # the gradient checked is the corrected path's own: the screen-space path's differs, in the depths above all
    affine = build_renderer(name, image_size=12, **_options(name))
    (affine_grad,) = torch.autograd.grad((affine(v, faces, TexturesVertex(colors)) * weights).sum(), v)
    assert (grad - affine_grad)[..., 2].abs().sum() > 0.1 * grad[..., 2].abs().sum() > 0


@pytest.mark.parametrize("group", ["layered", "softras", "hard"])
def test_the_renderer_config_group_sets_the_option(group, tmp_path):
    from tests.support.training import compose_config
    from unicorn.config import model_config, validate

    out = f"paths.output_dir={tmp_path}"
    default = model_config(validate(compose_config([f"renderer={group}", out])))["renderer"]["options"]
    assert default["perspective_correct"] is False
    settings = model_config(validate(compose_config([f"renderer={group}", "renderer.perspective_correct=true", out])))
    options = settings["renderer"]["options"]
    assert options["perspective_correct"] is True
    assert build_renderer(settings["renderer"]["name"], **options).rasterizer.perspective_correct is True


def test_a_perspective_correct_that_is_not_a_boolean_is_refused_at_composition(tmp_path):
    from tests.support.training import compose_config
    from unicorn.config import ConfigError, validate

    with pytest.raises(ConfigError, match="renderer.perspective_correct must be True or False, got 'maybe'"):
        validate(compose_config(["renderer.perspective_correct=maybe", f"paths.output_dir={tmp_path}"]))
