"""Texture sampling: bilinear lookups, and the seam of the spherical UVs."""

import math

import torch
import torch.nn.functional as nnf

from unicorn.geometry.mesh import ellipsoid, spherical_face_uvs, spherical_vertex_uvs
from unicorn.geometry.rotations import look_at_view_transform
from unicorn.render import LayeredRasterizer, TexturesUV
from unicorn.render.textures import sample_bilinear


def test_bilinear_matches_grid_sample():
    maps = torch.rand(2, 3, 7, 9, dtype=torch.float64)
    uv = torch.rand(50, 2, dtype=torch.float64) * 1.2 - 0.1
    b = torch.randint(0, 2, (50,))
    for align in (True, False):
        ours = sample_bilinear(maps, b, uv, wrap_u=False, align_corners=align)
        grid = torch.stack([uv[:, 0] * 2 - 1, (1 - uv[:, 1]) * 2 - 1], -1)  # v = 0 is the bottom row
        ref = torch.stack(
            [
                nnf.grid_sample(
                    maps[i : i + 1], grid[None, None, j : j + 1], align_corners=align, padding_mode="border"
                )[0, :, 0, 0]
                for j, i in enumerate(b.tolist())
            ]
        )
        assert torch.allclose(ours, ref)


def test_wrap_u_is_periodic():
    maps = torch.rand(1, 3, 4, 8, dtype=torch.float64)
    uv = torch.rand(20, 2, dtype=torch.float64)
    b = torch.zeros(20, dtype=torch.long)
    a = sample_bilinear(maps, b, uv, wrap_u=True, align_corners=False)
    shifted = sample_bilinear(
        maps, b, uv + torch.tensor([1.0, 0.0], dtype=torch.float64), wrap_u=True, align_corners=False
    )
    assert torch.allclose(a, shifted)


def _azimuth_texture(width: int = 64):
    # colour = smooth periodic function of the azimuth: red = (1 + cos)/2, green = (1 + sin)/2
    u = (torch.arange(width) + 0.5) / width
    phi = 2 * math.pi * u - math.pi
    row = torch.stack([(1 + phi.cos()) / 2, (1 + phi.sin()) / 2, torch.full_like(phi, 0.5)])
    return row[:, None, :].expand(3, 32, width).clone()[None]


def test_seam_faces_sample_across_the_seam():
    v, f = ellipsoid(3, scale=0.6)
    # look at the seam (x = 0, z < 0): the camera sits on -Z
    R, T = look_at_view_transform(2.0, 0.0, 180.0)
    tex = _azimuth_texture()
    renderer = LayeredRasterizer(image_size=64)
    ours = renderer(v[None], f, TexturesUV(tex, spherical_face_uvs(v, f), wrap_u=True), R=R, T=T)
    naive_uvs = spherical_vertex_uvs(v)[f]
    naive = renderer(v[None], f, TexturesUV(tex, naive_uvs, wrap_u=False), R=R, T=T)
    # expected colour from the visible surface point's azimuth: near the seam phi = +-pi, so red = 0, green = 0.5
    out = renderer.render(v[None], f, TexturesUV(tex, spherical_face_uvs(v, f)), R=R, T=T)
    ids = out.face_ids[0]
    centre_cols = slice(28, 36)
    covered = ids[:, centre_cols] >= 0
    red_ours = ours[0, 0, :, centre_cols][covered]
    red_naive = naive[0, 0, :, centre_cols][covered]
    assert red_ours.max() < 0.08  # the seam column is red-free as it should be
    assert red_naive.max() > 0.4  # the reference UVs smear the whole texture across seam faces
