"""Compositing variants, chosen by name: each against the renderer called directly."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import IMAGE_SIZE, randomize_heads, tiny_config
from unicorn.model import ReferenceCompositing, Unicorn, build_compositing, list_compositings

pytestmark = pytest.mark.filterwarnings("ignore:some pixels had more than faces_per_pixel")


def test_registry_names_and_unknown_name():
    assert list_compositings() == ["direct", "reference"]
    assert isinstance(build_compositing("reference"), ReferenceCompositing)
    with pytest.raises(ValueError, match=r"unknown compositing 'over'; known: \['direct', 'reference'\]"):
        build_compositing("over")


@pytest.mark.parametrize("composite", ["direct", "reference"])
def test_model_renders_with_the_configured_compositing(composite, images):
    torch.manual_seed(0)
    cfg = tiny_config("real")
    cfg["renderer"]["composite"] = composite
    model = Unicorn(cfg).eval()
    randomize_heads(model)
    with torch.no_grad():
        pred = model.predict(images)
        rgb, alpha = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
        textures, faces = model.textures(pred.texture), model.template.faces
        if composite == "direct":
            want = model.renderer(pred.verts, faces, textures, R=pred.R, T=pred.T, background=pred.background)
        else:
            out = model.renderer(pred.verts, faces, textures, R=pred.R, T=pred.T)
            want = torch.cat([out[:, :3] * out[:, 3:] + (1 - out[:, 3:]) * pred.background, out[:, 3:]], 1)
        # without a background image both render over the renderer's background colour
        plain = model.renderer(pred.verts, faces, textures, R=pred.R, T=pred.T)
        no_bkg = model.render(pred.verts, pred.texture, pred.R, pred.T, None)
    assert rgb.shape == (images.shape[0], 3, IMAGE_SIZE, IMAGE_SIZE)
    torch.testing.assert_close(torch.cat([rgb, alpha], 1), want)
    torch.testing.assert_close(torch.cat(no_bkg, 1), plain)
    assert 0 < float(alpha.mean()) < 1  # an object and some background in view


def test_the_two_compositings_differ_only_where_the_silhouette_is_soft(images):
    """Where the object covers a pixel fully or not at all both give the same colour (the object's, the background
    image's); at the soft silhouette ``direct`` blends the background image inside the renderer's aggregation, unlike
    ``reference``'s ``rgb * A + (1 - A) * background`` over the background colour."""
    torch.manual_seed(0)
    renders = {}
    for composite in ("direct", "reference"):
        cfg = tiny_config("real")
        cfg["renderer"]["composite"] = composite
        torch.manual_seed(0)
        model = Unicorn(cfg).eval()
        randomize_heads(model)
        with torch.no_grad():
            pred = model.predict(images)
            renders[composite] = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    (rgb_d, alpha_d), (rgb_r, alpha_r) = renders["direct"], renders["reference"]
    torch.testing.assert_close(alpha_d, alpha_r)
    gap = (rgb_d - rgb_r).abs().amax(1, keepdim=True)
    hard = (alpha_d == 0) | (alpha_d > 1 - 1e-6)
    soft = (alpha_d > 0.05) & (alpha_d < 0.95)
    assert hard.any() and soft.sum() > 10
    assert gap[hard].max() < 1e-5
    assert (gap[soft] > 1e-3).float().mean() > 0.5
    background = pred.background.expand_as(rgb_d)
    empty = (alpha_d == 0).expand_as(rgb_d)
    torch.testing.assert_close(rgb_d[empty], background[empty])  # nothing there: the background image itself
