"""TexturesUV takes PyTorch3D's channels-last maps as well as (B, C, Ht, Wt), and says which layouts it knows."""

import pytest
import torch

from tests.support.render import template_scene
from unicorn.render import TexturesUV, build_renderer


def test_pytorch3d_channels_last_maps_render_like_channels_first():
    verts, faces, R, T, uvs = template_scene(batch=2)
    maps = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    renderer = build_renderer("layered", image_size=32)
    expected = renderer(verts, faces, TexturesUV(maps, uvs), R=R, T=T)
    pytorch3d_layout = maps.permute(0, 2, 3, 1).contiguous()  # PyTorch3D's (B, Ht, Wt, C)
    textures = TexturesUV(pytorch3d_layout, uvs)
    assert textures.maps.shape == (2, 3, 16, 16) and textures.num_channels == 3
    torch.testing.assert_close(renderer(verts, faces, textures, R=R, T=T), expected)
    # a shape that reads both ways (4 channels of 4 x 3, or 3 of 4 x 4) needs the layout said
    tiny = torch.rand(1, 4, 4, 3)
    assert TexturesUV(tiny, uvs, channels_last=True).maps.shape == (1, 3, 4, 4)
    assert TexturesUV(tiny, uvs, channels_last=False).maps.shape == (1, 4, 4, 3)
    with pytest.raises(ValueError, match=r"^maps \(1, 4, 4, 3\) reads as .* say which with channels_last"):
        TexturesUV(tiny, uvs)


def test_other_shapes_are_refused_at_construction_naming_the_layouts():
    _, _, _, _, uvs = template_scene(batch=1)
    with pytest.raises(
        ValueError, match=r"^maps must have shape \(B, C, Ht, Wt\) or \(B, Ht, Wt, C\), got \(16, 16, 3\)$"
    ):
        TexturesUV(torch.rand(16, 16, 3), uvs)


def test_integer_uvs_are_named() -> None:
    with pytest.raises(TypeError, match="face_uvs must be a floating point tensor, got torch.int64"):
        TexturesUV(torch.rand(1, 3, 8, 8), torch.zeros(4, 3, 2, dtype=torch.long))  # they would sample one texel
