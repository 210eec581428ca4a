import math

import pytest
import torch

from unicorn.geometry.mesh import (
    ellipsoid,
    icosphere,
    mirror_points,
    mirror_spherical_map,
    spherical_face_uvs,
    spherical_vertex_uvs,
)


def test_icosphere_sizes_and_orientation():
    for level, (nv, nf) in {3: (642, 1280), 4: (2562, 5120)}.items():
        v, f = icosphere(level)
        assert v.shape == (nv, 3) and f.shape == (nf, 3)
        assert torch.allclose(v.norm(dim=-1), torch.ones(nv), atol=1e-5)
        # outward normals: the face normal points along the face centre
        tri = v[f]
        n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
        assert ((n * tri.mean(1)).sum(-1) > 0).all()


def test_icosphere_refuses_a_level_that_is_no_whole_number_in_range():
    for bad in (True, 1.5, float("nan"), "2", -1, 8):
        with pytest.raises(ValueError, match=r"icosphere level must be a whole number in \[0, 7\], got"):
            icosphere(bad)
    assert torch.equal(icosphere(2.0)[1], icosphere(2)[1])  # 2.0 is 2


@pytest.mark.parametrize("dtype", [torch.long, torch.int32, torch.bool, torch.complex64, "float32"], ids=str)
def test_icosphere_refuses_a_dtype_that_cannot_hold_its_vertices(dtype):
    # an integer dtype would round the unit sphere's coordinates to -1, 0 and 1
    with pytest.raises(TypeError, match=r"^icosphere dtype must be a floating point torch dtype, got "):
        icosphere(1, dtype=dtype)
    assert icosphere(1, dtype=torch.float16)[0].dtype == torch.float16


def test_ellipsoid_axes():
    v, _ = ellipsoid(3, scale=0.6)
    assert torch.allclose(v.abs().amax(0), torch.tensor([0.6, 0.42, 0.42]), atol=1e-3)


def test_ellipsoid_bottom_squashes_the_lower_half_only():
    full, faces = ellipsoid(3, scale=0.6)
    dome, dome_faces = ellipsoid(3, scale=0.6, bottom=0.25)
    assert torch.equal(faces, dome_faces)
    upper = full[:, 1] >= 0
    assert torch.equal(dome[upper], full[upper])
    assert torch.allclose(dome[~upper], full[~upper] * torch.tensor([1.0, 0.25, 1.0]))
    assert dome[:, 1].min() == pytest.approx(-0.42 * 0.25, abs=1e-3) and dome[:, 1].max() == pytest.approx(
        0.42, abs=1e-3
    )
    # no longer up-down symmetric: the flipped dome is not the dome
    flipped = dome * torch.tensor([1.0, -1.0, 1.0])
    assert torch.cdist(flipped, dome).amin(1).max() > 0.1


def test_reference_uvs_straddle_the_seam_and_ours_do_not():
    v, f = ellipsoid(3, scale=0.6)
    ref = spherical_vertex_uvs(v)[f][..., 0]
    assert int(((ref.amax(1) - ref.amin(1)) > 0.5).sum()) == 45  # the reference's 45 of 1280 faces
    ours = spherical_face_uvs(v, f)
    span = ours[..., 0].amax(1) - ours[..., 0].amin(1)
    assert span.max() < 0.25
    assert ours[..., 0].min() >= 0 and ours[..., 0].max() < 1.5
    assert torch.allclose(ours[..., 1], spherical_vertex_uvs(v)[f][..., 1])


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda v, f: spherical_vertex_uvs(v[None]), r"verts must have shape \(V, 3\), got \(1, 42, 3\)"),
        (lambda v, f: spherical_face_uvs(v[None], f), r"verts must have shape \(V, 3\), got \(1, 42, 3\)"),
        (lambda v, f: spherical_face_uvs(v, f[None]), r"faces must have shape \(F, 3\), got \(1, 80, 3\)"),
        (lambda v, f: spherical_face_uvs(v, f + 1), r"face indices must be in \[0, 42\)"),
    ],
    ids=["vertex-batch", "face-batch", "faces-batch", "faces-range"],
)
def test_spherical_uvs_name_a_batch_of_meshes(call, match):
    # a renderer's vertices are (B, V, 3): the UVs are one mesh's, said in one line
    v, f = icosphere(1)
    with pytest.raises(ValueError, match=match):
        call(v, f)


def _periodic_bilinear(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Naive texel-centred bilinear lookup of ``image`` (C, H, W) at ``uv`` (N, 2), periodic in u: (N, C)."""
    c, h, w = image.shape
    out = []
    for u, v in uv.tolist():
        x, y = u * w - 0.5, min(max(v * h - 0.5, 0.0), h - 1.0)
        x0, y0 = math.floor(x), min(math.floor(y), h - 2)
        fx, fy = x - x0, y - y0
        value = torch.zeros(c)
        for dx, wx in ((0, 1 - fx), (1, fx)):
            for dy, wy in ((0, 1 - fy), (1, fy)):
                value += wx * wy * image[:, y0 + dy, (x0 + dx) % w]
        out.append(value)
    return torch.stack(out)


def test_icosphere_is_mirror_symmetric_in_z():
    v, _ = icosphere(3, dtype=torch.float64)
    mirrored = mirror_points(v)
    assert torch.cdist(mirrored, v).min(dim=1).values.max() < 1e-5
    assert torch.equal(mirror_points(v)[:, :2], v[:, :2]) and torch.equal(mirror_points(v)[:, 2], -v[:, 2])


@pytest.mark.parametrize("shape", [(4, 2), (4, 1), (3, 4), ()], ids=str)
def test_mirror_points_names_points_that_are_not_3d(shape):
    # (4, 1) would broadcast to (4, 3) without a word
    with pytest.raises(ValueError, match=r"^points must have shape \(\.\.\., 3\), got "):
        mirror_points(torch.ones(shape))


def test_mirrored_map_shows_at_a_point_what_the_map_shows_at_its_mirror():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, 8, 16, generator=g)
    points = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1)
    seen = _periodic_bilinear(image, spherical_vertex_uvs(points))
    mirrored = _periodic_bilinear(mirror_spherical_map(image), spherical_vertex_uvs(mirror_points(points)))
    assert torch.allclose(mirrored, seen, atol=1e-5)
    # the lookup is not mirror-symmetric by itself: the oracle can tell the maps apart
    assert not torch.allclose(_periodic_bilinear(image, spherical_vertex_uvs(mirror_points(points))), seen, atol=0.1)
    assert torch.equal(mirror_spherical_map(mirror_spherical_map(image)), image)
    with pytest.raises(ValueError, match="even width"):
        mirror_spherical_map(torch.rand(3, 8, 15))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"scale": 0.0}, r"^ellipsoid scale must be a finite number > 0, got 0\.0$"),
        ({"scale": -0.6}, r"^ellipsoid scale must be a finite number > 0, got -0\.6$"),
        ({"scale": float("nan")}, r"^ellipsoid scale must be a finite number > 0, got nan$"),
        ({"scale": float("inf")}, r"^ellipsoid scale must be a finite number > 0, got inf$"),
        ({"scale": True}, r"^ellipsoid scale must be a finite number > 0, got True$"),
        ({"axes": (1.0, 0.7)}, r"^ellipsoid axes must be three finite numbers > 0 \(x, y, z\), got \(1\.0, 0\.7\)$"),
        ({"axes": (1.0, 0.7, 0.7, 1.0)}, r"^ellipsoid axes must be three finite numbers > 0"),
        ({"axes": (1.0, -0.7, 0.7)}, r"^ellipsoid axes must be .*, got \(1\.0, -0\.7, 0\.7\)$"),
        ({"axes": (1.0, 0.0, 0.7)}, r"^ellipsoid axes must be three finite numbers > 0"),
        ({"axes": (1.0, float("nan"), 0.7)}, r"^ellipsoid axes must be three finite numbers > 0"),
        ({"axes": 0.7}, r"^ellipsoid axes must be three finite numbers > 0 .*, got 0\.7$"),
        ({"axes": "abc"}, r"^ellipsoid axes must be three finite numbers > 0"),
        ({"bottom": 0.0}, r"^ellipsoid bottom must be a number in \(0, 1\], got 0\.0$"),
        ({"bottom": -0.5}, r"^ellipsoid bottom must be a number in \(0, 1\], got -0\.5$"),
        ({"bottom": 1.5}, r"^ellipsoid bottom must be a number in \(0, 1\], got 1\.5$"),
        ({"bottom": float("nan")}, r"^ellipsoid bottom must be a number in \(0, 1\], got nan$"),
    ],
)
def test_ellipsoid_refuses_a_stretch_that_builds_no_template(kwargs, match):
    # each of these would give a flat, inside-out or NaN template (or torch's broadcasting error) without a word
    with pytest.raises(ValueError, match=match):
        ellipsoid(1, **kwargs)


def test_ellipsoid_takes_any_real_numbers_and_keeps_faces_outward():
    np = pytest.importorskip("numpy")
    v, f = ellipsoid(2, np.array([1.0, 0.5, 0.3]), np.float32(0.6), bottom=1)
    assert torch.allclose(v.abs().amax(0), torch.tensor([0.6, 0.3, 0.18]), atol=1e-3)
    tri = v[f]
    n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    assert ((n * tri.mean(1)).sum(-1) > 0).all()  # outward: a convex shape's faces point away from its centre
    assert torch.isfinite(ellipsoid(1, bottom=1e-3)[0]).all()
