import torch

from unicorn.geometry.mesh import ellipsoid, icosphere, spherical_face_uvs, spherical_vertex_uvs


def test_icosphere_sizes_and_orientation():
    for level, (nv, nf) in {3: (642, 1280), 4: (2562, 5120)}.items():
        v, f = icosphere(level)
        assert v.shape == (nv, 3) and f.shape == (nf, 3)
        assert torch.allclose(v.norm(dim=-1), torch.ones(nv), atol=1e-5)
        # outward normals: the face normal points along the face centre
        tri = v[f]
        n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
        assert ((n * tri.mean(1)).sum(-1) > 0).all()


def test_ellipsoid_axes():
    v, _ = ellipsoid(3, scale=0.6)
    assert torch.allclose(v.abs().amax(0), torch.tensor([0.6, 0.42, 0.42]), atol=1e-3)


def test_reference_uvs_straddle_the_seam_and_ours_do_not():
    v, f = ellipsoid(3, scale=0.6)
    ref = spherical_vertex_uvs(v)[f][..., 0]
    assert int(((ref.amax(1) - ref.amin(1)) > 0.5).sum()) == 45  # the reference's 45 of 1280 faces
    ours = spherical_face_uvs(v, f)
    span = ours[..., 0].amax(1) - ours[..., 0].amin(1)
    assert span.max() < 0.25
    assert ours[..., 0].min() >= 0 and ours[..., 0].max() < 1.5
    assert torch.allclose(ours[..., 1], spherical_vertex_uvs(v)[f][..., 1])
