"""Every backend renders in float32 under autocast: the same images as a float32 run, whatever autocast does."""

from __future__ import annotations

import pytest
import torch

from tests.support.render import template_scene
from unicorn.render import TexturesUV, TexturesVertex, build_renderer, list_renderers
from unicorn.render.precision import (
    _device_type,
    autocast_active,
    float32_boundary,
    full_precision,
    to_full_precision,
)


def bf16_autocast():
    return torch.autocast("cpu", dtype=torch.bfloat16)


def _scene():
    verts, faces, R, T, uvs = template_scene(batch=2)
    g = torch.Generator().manual_seed(3)
    maps = torch.rand(2, 3, 8, 8, generator=g)
    background = torch.rand(2, 3, 16, 16, generator=g)
    return verts, faces, R, T, uvs, maps, background


@pytest.mark.parametrize("name", list_renderers())
def test_float32_inputs_render_the_same_images_under_autocast(name):
    renderer = build_renderer(name, image_size=16)
    verts, faces, R, T, uvs, maps, background = _scene()
    expected = renderer(verts, faces, TexturesUV(maps, uvs), R=R, T=T, background=background)
    with bf16_autocast():
        images = renderer(verts, faces, TexturesUV(maps, uvs), R=R, T=T, background=background)
    assert images.dtype == torch.float32
    assert torch.equal(images, expected)


@pytest.mark.parametrize("name", list_renderers())
def test_bfloat16_inputs_are_rendered_in_float32_under_autocast(name):
    """Reduced-precision textures, pose and background (what autocast's layers give) are cast, not rejected; the
    images are the float32 render of the cast values, and gradients reach the bfloat16 inputs in their dtype."""
    renderer = build_renderer(name, image_size=16)
    verts, faces, R, T, uvs, maps, background = _scene()
    maps16, R16, bg16 = maps.bfloat16().requires_grad_(), R.bfloat16(), background.bfloat16()
    colors16 = torch.rand(2, verts.shape[1], 3).bfloat16()
    expected = renderer(verts, faces, TexturesUV(maps16.detach().float(), uvs), R=R16.float(), T=T,
                        background=bg16.float())  # fmt: skip
    expected_vertex = renderer(verts.bfloat16().float(), faces, TexturesVertex(colors16.float()), R=R, T=T)
    with bf16_autocast():
        images = renderer(verts, faces, TexturesUV(maps16, uvs), R=R16, T=T, background=bg16)
        vertex = renderer(verts.bfloat16(), faces, TexturesVertex(colors16), R=R, T=T)
    assert images.dtype == vertex.dtype == torch.float32
    assert torch.equal(images, expected) and torch.equal(vertex, expected_vertex)
    images.sum().backward()
    assert maps16.grad is not None and maps16.grad.dtype == torch.bfloat16


def test_fragments_are_float32_under_autocast():
    renderer = build_renderer("layered", image_size=16)
    verts, faces, R, T, *_ = _scene()
    R16 = R.bfloat16()
    expected = renderer.rasterize(verts, faces, R16.float(), T)
    with bf16_autocast():
        fragments = renderer.rasterize(verts, faces, R16, T)
    assert fragments.bary.dtype == fragments.zbuf.dtype == fragments.dists.dtype == torch.float32
    for name in ("pix", "face", "bary", "dists", "zbuf"):
        assert torch.equal(getattr(fragments, name), getattr(expected, name)), name


def test_outside_autocast_nothing_is_cast():
    x = torch.ones(2, dtype=torch.bfloat16)
    assert not autocast_active("cpu")
    with full_precision("cpu"):
        assert not autocast_active("cpu")
    with bf16_autocast():
        assert autocast_active("cpu")
        with full_precision("cpu"):
            assert not autocast_active("cpu")
            assert (x.float() @ x.float()).dtype == torch.float32
        assert autocast_active("cpu")
    assert to_full_precision(x).dtype == torch.float32
    assert to_full_precision(x.double()).dtype == torch.float64 and to_full_precision(None) is None


class _Probe:
    """Records what a method behind the boundary receives."""

    @float32_boundary
    def run(self, verts, textures, scale=None, name="x"):
        mm = verts @ verts.transpose(-1, -2)  # a matmul: bfloat16 if autocast were still on
        return verts.dtype, textures.maps.dtype, None if scale is None else scale.dtype, name, mm.dtype


def test_the_boundary_casts_16_bit_arguments_and_turns_autocast_off():
    verts = torch.rand(1, 4, 3)
    maps, uvs = torch.rand(1, 3, 4, 4), torch.rand(2, 3, 2)
    probe = _Probe()
    with bf16_autocast():
        got = probe.run(
            verts.bfloat16(), TexturesUV(maps.half(), uvs, channels_last=False), scale=torch.ones(2).double(), name="y"
        )
    assert got == (torch.float32, torch.float32, torch.float64, "y", torch.float32)
    # outside autocast the arguments pass untouched
    got = probe.run(verts.bfloat16(), TexturesUV(maps.half(), uvs, channels_last=False))
    assert got[:3] == (torch.bfloat16, torch.float16, None) and got[4] == torch.bfloat16


def test_the_boundary_reads_the_device_of_arguments_given_by_keyword():
    meta = torch.empty(1, 4, 3, device="meta")
    assert _device_type((object(), meta), {}) == "meta"
    assert _device_type((object(),), {"verts": meta, "faces": torch.zeros(1, 3)}) == "meta"  # not the default, cpu
    assert _device_type((object(), 2.0), {"name": "y"}) == "cpu"


@pytest.mark.gpu
@pytest.mark.parametrize("name", list_renderers())
def test_keyword_arguments_render_in_float32_under_cuda_autocast(name):
    renderer = build_renderer(name, image_size=16).cuda()
    verts, faces, R, T, uvs, maps, background = (t.cuda() for t in _scene())
    expected = renderer.render(verts=verts, faces=faces, textures=TexturesUV(maps, uvs), R=R, T=T)
    with torch.autocast("cuda", dtype=torch.float16):
        images = renderer.render(verts=verts, faces=faces, textures=TexturesUV(maps, uvs), R=R, T=T)
    assert torch.equal(images.images, expected.images)
