"""Bad input: a clear error, or a defined output with no NaN in values or gradients."""

import re

import pytest
import torch

from tests.support.render import template_scene
from unicorn.render import (
    DEFAULT_MAX_RENDER_BYTES,
    MAX_RENDER_BYTES_ENV,
    LayeredRasterizer,
    MeshRasterizer,
    TexturesUV,
    TexturesVertex,
    build_renderer,
    list_renderers,
    rasterize_meshes,
)


@pytest.fixture(params=list_renderers())
def renderer(request):
    return build_renderer(request.param, image_size=16)


def _tex(B, V, dtype=torch.float32):
    return TexturesVertex(torch.rand(B, V, 3, dtype=dtype))


@pytest.mark.parametrize(
    ("verts", "faces", "error", "match"),
    [
        (torch.zeros(5, 3), torch.tensor([[0, 1, 2]]), ValueError, r"verts must have shape \(B, V, 3\)"),
        (torch.zeros(1, 5, 2), torch.tensor([[0, 1, 2]]), ValueError, r"verts must have shape \(B, V, 3\)"),
        (torch.zeros(1, 5, 3, dtype=torch.int64), torch.tensor([[0, 1, 2]]), TypeError, "float32 or float64"),
        (
            torch.zeros(1, 5, 3, dtype=torch.float16),
            torch.tensor([[0, 1, 2]]),
            TypeError,
            "float32 or float64",
        ),
        (torch.zeros(1, 5, 3), torch.tensor([0, 1, 2]), ValueError, r"faces must have shape \(F, 3\)"),
        (torch.zeros(1, 5, 3), torch.tensor([[0.0, 1.0, 2.0]]), TypeError, "integer"),
        (
            torch.zeros(1, 5, 3),
            torch.tensor([[0, 1, 2]], dtype=torch.uint16),  # torch has no min, max or gather for it
            TypeError,
            r"faces must be an integer tensor of int64, int32, .* got torch.uint16",
        ),
        (torch.zeros(1, 5, 3, device="meta"), torch.zeros(1, 3, dtype=torch.int64, device="meta"), ValueError, "meta"),
        (torch.zeros(1, 5, 3), torch.tensor([[0, 1, 5]]), IndexError, r"face indices must be in \[0, 5\)"),
        (torch.zeros(1, 5, 3), torch.tensor([[0, -1, 2]]), IndexError, "face indices"),
        (
            torch.tensor([[[0, 0, 1.0], [float("nan"), 0, 1], [0, 1, 1]]]),
            torch.tensor([[0, 1, 2]]),
            ValueError,
            "NaN or infinite",
        ),
        (
            torch.tensor([[[0, 0, 1.0], [float("inf"), 0, 1], [0, 1, 1]]]),
            torch.tensor([[0, 1, 2]]),
            ValueError,
            "NaN or infinite",
        ),
    ],
)
def test_bad_meshes_raise_clear_errors(renderer, verts, faces, error, match):
    B, V = verts.shape[0] if verts.dim() == 3 else 1, verts.shape[-2]
    with pytest.raises(error, match=match):
        renderer(verts, faces, _tex(B, V))


def test_bad_pose_and_texture_arguments(renderer):
    verts, faces, R, T, uvs = template_scene(batch=2)
    tex = _tex(2, verts.shape[1])
    with pytest.raises(ValueError, match=r"R must have shape \(2, 3, 3\)"):
        renderer(verts, faces, tex, R=R[:1], T=T)
    with pytest.raises(ValueError, match="give both R and T"):
        renderer(verts, faces, tex, R=R)
    with pytest.raises(ValueError, match="batch size 3"):
        renderer(verts, faces, _tex(3, verts.shape[1]), R=R, T=T)
    with pytest.raises(TypeError, match="TexturesUV or TexturesVertex"):
        renderer(verts, faces, torch.rand(2, verts.shape[1], 3), R=R, T=T)
    with pytest.raises(ValueError, match=r"maps must have shape \(B, C, Ht, Wt\)"):
        TexturesUV(torch.rand(2, 3, 8), uvs)
    with pytest.raises(ValueError, match=r"maps needs at least one channel and one texel, got .* \(2, 3, 0, 8\)"):
        TexturesUV(torch.rand(2, 3, 0, 8), uvs)
    with pytest.raises(ValueError, match=r"face_uvs must have shape \(F, 3, 2\)"):
        TexturesUV(torch.rand(2, 3, 8, 8), uvs[..., :1])
    with pytest.raises(ValueError, match="wrap_u=True needs align_corners=False"):
        TexturesUV(torch.rand(2, 3, 8, 8), uvs, wrap_u=True, align_corners=True)


def test_bad_settings():
    with pytest.raises(ValueError, match="faces_per_pixel"):
        LayeredRasterizer(faces_per_pixel=0)
    with pytest.raises(ValueError, match="sigma"):
        LayeredRasterizer(sigma=-1.0)
    with pytest.raises(ValueError, match="image_size"):
        LayeredRasterizer(image_size=0)
    for gamma in (0.0, -1.0):  # SoftRas divides by it: > 0, as the settings and the backend both say
        with pytest.raises(ValueError, match=rf"^gamma must be a finite number > 0, got {gamma}$"):
            build_renderer("softras", gamma=gamma)


def test_degenerate_geometry_gives_defined_output_and_finite_gradients(renderer):
    # one face behind the camera, one crossing the camera plane, one of zero area, one ordinary face
    verts = torch.tensor(
        [
            [
                [0.0, 0.0, -2.0],
                [0.3, 0.0, -2.0],
                [0.0, 0.3, -2.0],
                [0.0, 0.0, -1.0],
                [0.3, 0.0, 2.0],
                [0.0, 0.3, 2.0],
                [0.1, 0.1, 2.0],
                [0.2, 0.2, 2.0],
                [0.3, 0.3, 2.0],
                [0.1, -0.1, 2.5],
                [-0.2, -0.1, 2.5],
                [0.0, 0.2, 2.5],
            ]
        ],
        requires_grad=True,
    )
    faces = torch.arange(12).view(4, 3)
    colors = torch.rand(1, 12, 3, requires_grad=True)
    images = renderer(verts, faces, TexturesVertex(colors))  # R, T omitted: verts are in view space
    assert torch.isfinite(images).all()
    assert images[:, 3].max() > 0.99  # the ordinary face is drawn
    images.sum().backward()
    assert torch.isfinite(verts.grad).all() and torch.isfinite(colors.grad).all()
    # the skipped faces receive nothing
    assert verts.grad[0, :9].abs().sum() == 0


def test_faces_without_vertices_are_an_error(renderer):
    with pytest.raises(IndexError, match=r"face indices must be in \[0, 0\)"):
        renderer(torch.rand(2, 0, 3), torch.zeros(4, 3, dtype=torch.long), _tex(2, 0))


@pytest.mark.parametrize("shape", [(3, 0), (0, 0)])
def test_empty_meshes_render_background(renderer, shape):
    V, F = shape
    verts = torch.rand(2, V, 3, requires_grad=True)
    faces = torch.zeros(F, 3, dtype=torch.long)
    images = renderer(verts, faces, _tex(2, V))
    assert images.shape == (2, 4, 16, 16)
    assert torch.equal(images[:, 3], torch.zeros(2, 16, 16))
    assert torch.equal(images[:, :3], torch.ones(2, 3, 16, 16))


def test_empty_batch(renderer):
    verts, faces, R, T, _ = template_scene(batch=1)
    images = renderer(verts[:0], faces, _tex(0, verts.shape[1]), R=R[:0], T=T[:0])
    assert images.shape == (0, 4, 16, 16)


def test_mesh_entirely_off_screen_or_behind():
    verts, faces, R, T, _ = template_scene(batch=2)
    frags = rasterize_meshes(torch.cat([verts[:1] + 50.0, verts[1:] * torch.tensor([1.0, 1.0, -1.0]) - 3.0]), faces, 16)
    assert frags.num_pairs == 0 and frags.num_slots == 0
    assert frags.to_dense().pix_to_face.eq(-1).all()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_cameras_are_named(renderer, bad):
    verts, faces, R, T, _ = template_scene(batch=2)
    tex = _tex(2, verts.shape[1])
    R_bad, T_bad = R.clone(), T.clone()
    R_bad[1, 0, 2] = bad
    T_bad[0, 2] = bad
    with pytest.raises(ValueError, match="R contains NaN or infinite values"):
        renderer(verts, faces, tex, R=R_bad, T=T)
    with pytest.raises(ValueError, match="T contains NaN or infinite values"):
        renderer(verts, faces, tex, R=R, T=T_bad)
    with pytest.raises(ValueError, match="T contains NaN"):
        renderer.rasterize(verts, faces, R, T_bad)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -1.0, None, "1e-3", True])
def test_non_finite_blur_radius_and_sigma_are_named(bad):
    verts, faces, R, T, _ = template_scene(batch=1)
    message = rf"^blur_radius must be a finite number >= 0, got {re.escape(repr(bad))}$"
    with pytest.raises(ValueError, match=message):
        rasterize_meshes(verts, faces, 16, blur_radius=bad)
    with pytest.raises(ValueError, match=message):
        MeshRasterizer(blur_radius=bad)
    with pytest.raises(ValueError, match="sigma"):
        LayeredRasterizer(sigma=bad)
    with pytest.raises(ValueError, match="sigma"):
        build_renderer("softras", sigma=bad)
    with pytest.raises(ValueError, match="gamma must be a finite number > 0"):  # 0 too: SoftRas divides by it
        build_renderer("softras", gamma=bad)


def test_texture_sizes_must_match_the_mesh(renderer):
    verts, faces, R, T, uvs = template_scene(batch=2)
    with pytest.raises(ValueError, match=rf"colors have {verts.shape[1] - 1} vertices, meshes {verts.shape[1]}"):
        renderer(verts, faces, _tex(2, verts.shape[1] - 1), R=R, T=T)
    with pytest.raises(ValueError, match=rf"face_uvs has {faces.shape[0] - 2} faces, meshes {faces.shape[0]}"):
        renderer(verts, faces, TexturesUV(torch.rand(2, 3, 8, 8), uvs[:-2]), R=R, T=T)


def test_integer_poses_are_named(renderer):
    verts, faces, R, T, _ = template_scene(batch=2)
    tex = _tex(2, verts.shape[1])
    eye = torch.eye(3, dtype=torch.long).expand(2, 3, 3)
    with pytest.raises(TypeError, match="R must be a floating point tensor, got torch.int64"):
        renderer(verts, faces, tex, R=eye, T=T)
    with pytest.raises(TypeError, match="T must be a floating point tensor, got torch.int32"):
        renderer(verts, faces, tex, R=R, T=T.int())
    with pytest.raises(TypeError, match="R must be a floating point tensor"):
        renderer.rasterize(verts, faces, eye, T)


def test_mixed_precisions_are_named(renderer):
    verts, faces, R, T, uvs = template_scene(batch=2)
    V = verts.shape[1]
    with pytest.raises(TypeError, match="verts is torch.float64 but colors is torch.float32"):
        renderer(verts.double(), faces, _tex(2, V), R=R, T=T)
    with pytest.raises(TypeError, match="verts is torch.float32 but maps is torch.float64"):
        renderer(verts, faces, TexturesUV(torch.rand(2, 3, 8, 8, dtype=torch.float64), uvs), R=R, T=T)
    # one precision throughout renders; the pose follows the vertices' dtype
    images = renderer(verts.double(), faces, TexturesVertex(torch.rand(2, V, 3, dtype=torch.float64)), R=R, T=T)
    assert images.dtype == torch.float64 and images[:, 3].max() > 0.99


def test_textures_and_backgrounds_on_another_device_are_named(renderer):
    # the meta device stands in for a GPU: a tensor there is on another device than the CPU vertices
    verts, faces, R, T, uvs = template_scene(batch=2)
    V, meta = verts.shape[1], torch.device("meta")
    with pytest.raises(ValueError, match="^verts is on cpu but colors is on meta$"):
        renderer(verts, faces, TexturesVertex(torch.rand(2, V, 3, device=meta)), R=R, T=T)
    with pytest.raises(ValueError, match="^verts is on cpu but maps is on meta$"):
        renderer(verts, faces, TexturesUV(torch.rand(2, 3, 8, 8, device=meta), uvs), R=R, T=T)
    with pytest.raises(ValueError, match="^verts is on cpu but background is on meta$"):
        renderer(verts, faces, _tex(2, V), R=R, T=T, background=torch.rand(2, 3, 16, 16, device=meta))
    with pytest.raises(ValueError, match="^R is on meta but T is on cpu$"):
        renderer(verts, faces, _tex(2, V), R=R.to(meta), T=T)
    with pytest.raises(ValueError, match="^R is on cpu but T is on meta$"):
        renderer.rasterize(verts, faces, R, T.to(meta))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_textures_are_named(renderer, bad):
    verts, faces, R, T, uvs = template_scene(batch=2)
    colors = torch.rand(2, verts.shape[1], 3)
    colors[1, 7, 2] = bad
    with pytest.raises(ValueError, match="colors contains NaN or infinite values"):
        renderer(verts, faces, TexturesVertex(colors), R=R, T=T)
    maps = torch.rand(2, 3, 8, 8)
    maps[0, 1, 2, 3] = bad
    with pytest.raises(ValueError, match="maps contains NaN or infinite values"):
        renderer(verts, faces, TexturesUV(maps, uvs), R=R, T=T)
    bad_uvs = uvs.clone()
    bad_uvs[3, 1, 0] = bad
    with pytest.raises(ValueError, match="face_uvs contains NaN or infinite values"):
        renderer(verts, faces, TexturesUV(torch.rand(2, 3, 8, 8), bad_uvs), R=R, T=T)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_or_integer_backgrounds_are_named(renderer, bad):
    verts, faces, R, T, _ = template_scene(batch=2)
    tex = _tex(2, verts.shape[1])
    background = torch.rand(2, 3, 16, 16)
    background[1, 0, 3, 4] = bad
    with pytest.raises(ValueError, match="background contains NaN or infinite values"):
        renderer(verts, faces, tex, R=R, T=T, background=background)
    with pytest.raises(TypeError, match=r"background must be a floating-point tensor .*, got torch.uint8"):
        renderer(verts, faces, tex, R=R, T=T, background=torch.full((2, 3, 16, 16), 255, dtype=torch.uint8))
    ok = renderer(verts, faces, tex, R=R, T=T, background=torch.zeros(2, 3, 16, 16))
    assert torch.isfinite(ok).all()


def test_a_background_of_another_dtype_is_refused(renderer):
    # as textures of another dtype: no silent cast either way
    verts, faces, R, T, _ = template_scene(batch=2)
    tex = _tex(2, verts.shape[1])
    for dtype in (torch.float64, torch.float16):
        with pytest.raises(TypeError, match=f"verts is torch.float32 but background is {dtype}"):
            renderer(verts, faces, tex, R=R, T=T, background=torch.rand(2, 3, 16, 16, dtype=dtype))
    tex64, bg64 = _tex(2, verts.shape[1], torch.float64), torch.rand(2, 3, 16, 16, dtype=torch.float64)
    double = renderer(verts.double(), faces, tex64, R=R.double(), T=T.double(), background=bg64)
    assert double.dtype == torch.float64


def test_blend_functions_check_their_options():
    from unicorn.render import RenderError
    from unicorn.render.layered import layered_blend, layered_occupancy
    from unicorn.render.softras import SoftRasBlend, softras_blend

    verts, faces, R, T, _ = template_scene(batch=1)
    fragments = MeshRasterizer(image_size=8)(verts, faces, R, T)
    colors = torch.rand(fragments.face.shape[0], 3)
    bg = torch.ones(64, 3)
    for sigma in (-1e-4, float("nan"), float("inf")):
        with pytest.raises(RenderError, match="sigma must be finite and >= 0"):
            layered_blend(colors, fragments, bg, sigma)
        with pytest.raises(RenderError, match="sigma must be finite and >= 0"):
            layered_occupancy(fragments, sigma)
    for options in ({"zfar": float("inf")}, {"znear": 5.0, "zfar": 5.0}, {"eps": float("nan")}, {"znear": "a"}):
        with pytest.raises(RenderError, match="need finite 0 <= znear < zfar and a finite eps"):
            softras_blend(colors, fragments, bg, **options)
        with pytest.raises(RenderError, match="need finite 0 <= znear < zfar and a finite eps"):
            SoftRasBlend(**options)
    with pytest.raises(RenderError, match="sigma and gamma must be finite and > 0 in float32"):
        build_renderer("softras", gamma=1e-50)  # > 0, but 0 in float32: every weight 0 / 0
    with pytest.raises(RenderError, match="sigma and gamma must be finite and > 0 in float32"):
        softras_blend(colors, fragments, bg, gamma="1e-4")
    from unicorn.render.hard import HardBlend

    for bad in (2.5, float("nan"), 0):  # a count: 2.5 used to render as 2
        with pytest.raises(RenderError, match=f"supersample must be a whole number >= 1, got {bad}"):
            HardBlend(bad)
    for options in ({"faces_per_pixel": 2.5}, {"max_candidates": 0}, {"max_bytes": float("nan")}):
        with pytest.raises(RenderError, match=f"{next(iter(options))} must be a whole number"):
            rasterize_meshes(verts, faces, 8, **options)
    with pytest.raises(RenderError, match="perspective_correct must be True or False, got 'yes'"):
        rasterize_meshes(verts, faces, 8, perspective_correct="yes")


@pytest.mark.parametrize("name", ["layered", "softras"])
def test_a_blur_radius_whose_candidates_exceed_the_limit_is_refused(name):
    from unicorn.render import RenderSizeError

    verts, faces, R, T, _ = template_scene(batch=1)
    tex = _tex(1, verts.shape[1])
    blurred = build_renderer(name, image_size=32, sigma=10.0, max_bytes=4 << 20)  # every face covers every pixel
    match = r"the faces' bounding boxes, grown by the blur radius \(sigma\), cover [\d,]+ candidate face-pixel pairs"
    with pytest.raises(RenderSizeError, match=match):
        blurred(verts, faces, tex, R=R, T=T)
    sharp = build_renderer(name, image_size=32, max_bytes=4 << 20)  # the default sigma: well within the limit
    assert torch.isfinite(sharp(verts, faces, tex, R=R, T=T)).all()


def test_long_thin_faces_over_the_limit_are_refused_without_blaming_sigma():
    from unicorn.render import RenderSizeError

    t = torch.linspace(-0.9, 0.9, 60)[:, None]  # 60 slivers across the whole image, each box most of it
    a, b = torch.tensor([-1.0, -1.0, 4.0]) + 0 * t, torch.tensor([1.0, 1.0, 4.0]) + 0 * t
    c = b + torch.tensor([0.0, 0.002, 0.0])
    corners = torch.stack([a, b, c], 1) + torch.cat([0 * t, 0.01 * t, 0 * t], 1)[:, None]
    verts, faces = corners.reshape(1, -1, 3), torch.arange(180).view(60, 3)
    hard = build_renderer("hard", image_size=64, supersample=1, max_bytes=1 << 20)
    with pytest.raises(RenderSizeError, match=r"^the faces' bounding boxes cover [\d,]+ candidate") as error:
        hard(verts, faces, _tex(1, 180))
    assert "sigma" not in str(error.value) and "long thin" in str(error.value)


def test_numpy_scalars_are_accepted_as_settings_and_kept_as_python_numbers():
    import numpy as np

    from unicorn.render import RenderError

    renderer = build_renderer("layered", image_size=np.int64(16), faces_per_pixel=np.int64(4), sigma=np.float32(1e-4))
    settings = renderer.settings
    assert (settings.faces_per_pixel, settings.image_size) == (4, (16, 16)) and type(settings.faces_per_pixel) is int
    assert type(settings.sigma) is float and settings.sigma == pytest.approx(1e-4)
    with pytest.raises(RenderError, match=r"faces_per_pixel must be a whole number >= 1, got (np\.True_|True)$"):
        build_renderer("layered", faces_per_pixel=np.True_)


def test_numpy_scalars_are_numbers_to_the_softras_depth_range_and_temperatures():
    import numpy as np

    from unicorn.render import RenderError, SoftRasBlend

    verts, faces, R, T, _ = template_scene(batch=1)
    tex = _tex(1, verts.shape[1])
    python = build_renderer("softras", image_size=16, znear=0.5, zfar=50.0)(verts, faces, tex, R=R, T=T)
    numpy = build_renderer("softras", image_size=16, znear=np.float32(0.5), zfar=np.float32(50.0))
    assert torch.equal(numpy(verts, faces, tex, R=R, T=T), python)
    blend = SoftRasBlend(np.float32(2.0**-13), np.float32(2.0**-13), np.int64(1), np.int64(100), np.float32(0.5))
    assert (blend.sigma, blend.gamma, blend.znear, blend.zfar, blend.eps) == (2.0**-13, 2.0**-13, 1.0, 100.0, 0.5)
    with pytest.raises(RenderError, match="^need finite 0 <= znear < zfar and a finite eps, got znear=True"):
        SoftRasBlend(znear=True)
    with pytest.raises(RenderError, match="^sigma and gamma must be finite and > 0 in float32, got sigma=nan"):
        SoftRasBlend(sigma=np.float32("nan"))


def test_blur_radius_needs_an_occupancy_threshold_in_range():
    from unicorn.render import RenderError
    from unicorn.render.raster import blur_radius_from_sigma

    for eps in (0.0, 0.5, float("nan")):
        with pytest.raises(RenderError, match="eps must be in \\(0, 0.5\\)"):
            blur_radius_from_sigma(1e-4, eps=eps)


def test_vertex_attributes_must_be_floats_on_the_meshs_vertices():
    from unicorn.checks import FaceIndexError
    from unicorn.render import interpolate_vertex_attributes

    verts, faces, R, T, _ = template_scene(batch=1)
    fragments = MeshRasterizer(image_size=8)(verts, faces, R, T)
    V = verts.shape[1]
    values = interpolate_vertex_attributes(fragments, faces, torch.full((1, V, 2), 7.0))
    assert torch.allclose(values, torch.full_like(values, 7.0))  # barycentrics sum to one
    with pytest.raises(TypeError, match="attrs"):
        interpolate_vertex_attributes(fragments, faces, torch.full((1, V, 2), 7))  # would round the weights to 0
    with pytest.raises(FaceIndexError, match=f"face indices must be in \\[0, {V - 1}\\)"):
        interpolate_vertex_attributes(fragments, faces, torch.rand(1, V - 1, 2))
    with pytest.raises(TypeError, match="faces must be an integer tensor"):
        interpolate_vertex_attributes(fragments, faces.float(), torch.rand(1, V, 2))


@pytest.mark.parametrize("dtype", [torch.int32, torch.int16, torch.uint8], ids=str)
def test_vertex_attributes_interpolate_alike_with_every_accepted_face_dtype(dtype):
    from unicorn.render import interpolate_vertex_attributes

    verts, faces, R, T, _ = template_scene(batch=1, level=2)  # 162 vertices: indices fit in uint8
    fragments = MeshRasterizer(image_size=8)(verts, faces, R, T)
    shared, per_image = torch.rand(verts.shape[1], 2), torch.rand(1, verts.shape[1], 2)
    for attrs in (shared, per_image):
        expected = interpolate_vertex_attributes(fragments, faces, attrs)
        assert torch.equal(interpolate_vertex_attributes(fragments, faces.to(dtype), attrs), expected)


@pytest.mark.parametrize("name", list_renderers())
@pytest.mark.parametrize("size", [2.5, "abc", True, (16, 2.0), (16, 16, 16), -3])
def test_bad_image_sizes_are_named(name, size):
    with pytest.raises((TypeError, ValueError), match=r"^image_size must be"):
        build_renderer(name, image_size=size)


def test_a_camera_rasterizer_or_blend_of_another_kind_is_refused_when_built():
    from unicorn.render import LayeredBlend, MeshRenderer

    with pytest.raises(TypeError, match="camera must be a PerspectiveCamera or None, got str"):
        MeshRasterizer(image_size=8, camera="pinhole")
    with pytest.raises(TypeError, match="rasterizer must be an nn.Module .* got str"):
        MeshRenderer("rasterizer", LayeredBlend(1e-4))
    with pytest.raises(TypeError, match="blend must be an nn.Module .* got str"):
        MeshRenderer(MeshRasterizer(image_size=8), "layered")


def test_image_size_accepts_ints_and_pairs():
    verts, faces, R, T, _ = template_scene(batch=1)
    rasterizer = MeshRasterizer(image_size=8)
    assert rasterizer(verts, faces, R, T, image_size=6).image_size == (6, 6)  # per call, too
    assert rasterizer(verts, faces, R, T, image_size=(6, 4)).image_size == (6, 4)
    assert build_renderer("layered", image_size=(12, 20)).image_size == (12, 20)
    assert build_renderer("layered", image_size=[12, 20]).image_size == (12, 20)
    assert MeshRasterizer(image_size=torch.Size([8, 9])).image_size == (8, 9)


@pytest.mark.parametrize("name", ["layered", "softras", "hard"])
def test_a_10000_pixel_render_fails_before_allocating(name, monkeypatch):
    monkeypatch.delenv(MAX_RENDER_BYTES_ENV, raising=False)
    verts, faces, R, T, _ = template_scene(batch=1)
    renderer = build_renderer(name, image_size=10000)
    # never render for real if the defaults change: the bound must be over the default limit first
    (H, W), K = renderer.raster_size, renderer.rasterizer.faces_per_pixel
    assert H * W * K * 64 > DEFAULT_MAX_RENDER_BYTES
    with pytest.raises(ValueError, match=r"^image_size: 1 x \d+x\d+ pixels .* GiB of fragments .*MAX_RENDER_BYTES"):
        renderer(verts, faces, _tex(1, verts.shape[1]), R=R, T=T)


def test_every_backend_refuses_a_render_over_the_limit(renderer, monkeypatch):
    verts, faces, R, T, _ = template_scene(batch=1)
    tex = _tex(1, verts.shape[1])
    monkeypatch.setenv(MAX_RENDER_BYTES_ENV, "1000")  # the environment's limit, when the renderer is given none
    with pytest.raises(ValueError, match=r"image_size: 1 x \d+x\d+ pixels .* over the limit of 9.31e-07 GiB"):
        renderer(verts, faces, tex, R=R, T=T)
    monkeypatch.setenv(MAX_RENDER_BYTES_ENV, "0")  # no limit
    assert renderer(verts, faces, tex, R=R, T=T).shape == (1, 4, 16, 16)


@pytest.mark.parametrize("name", ["layered", "softras", "hard"])
def test_the_built_in_backends_take_the_memory_limit_as_an_option(name, monkeypatch):
    monkeypatch.setenv(MAX_RENDER_BYTES_ENV, "1000")  # the option wins over the environment
    verts, faces, R, T, _ = template_scene(batch=1)
    tex = _tex(1, verts.shape[1])
    with pytest.raises(ValueError, match="over the limit of 1.86e-06 GiB"):
        build_renderer(name, image_size=16, max_bytes=2000)(verts, faces, tex, R=R, T=T)
    assert build_renderer(name, image_size=16, max_bytes=0)(verts, faces, tex, R=R, T=T).shape == (1, 4, 16, 16)
    with pytest.raises(ValueError, match="max_bytes must be a whole number >= 0, got -1"):
        build_renderer(name, max_bytes=-1)


def test_render_size_bound():
    from unicorn.render import check_render_size

    check_render_size(192, (64, 64), 25, max_bytes=192 * 64 * 64 * 25 * 64)  # exactly at the limit
    with pytest.raises(ValueError, match=r"faces_per_pixel=25 may need 1\.17 GiB"):
        check_render_size(192, (64, 64), 25, max_bytes=192 * 64 * 64 * 25 * 64 - 1)
    check_render_size(10**6, (10**4, 10**4), 50, max_bytes=0)  # 0: no limit


@pytest.mark.parametrize(
    ("supersample", "blend", "args"),
    [
        (2, "HardBlend", (1,)),
        (1, "HardBlend", (2,)),
        (3, "HardBlend", (2,)),
        (2, "LayeredBlend", ()),
        (2, "SoftRasBlend", ()),
    ],
)
def test_a_blend_that_does_not_take_the_rasterizers_supersampling_is_refused_when_built(supersample, blend, args):
    import unicorn.render
    from unicorn.render import MeshRenderer, RenderError

    made = getattr(unicorn.render, blend)(*args)
    message = rf"^the rasterizer supersamples {supersample} times but the blend {blend} averages"
    with pytest.raises(RenderError, match=message):
        MeshRenderer(MeshRasterizer(8, supersample=supersample), made)


def test_a_hand_made_supersampled_hard_renderer_renders_as_the_hard_backend():
    from unicorn.render import HardBlend, MeshRenderer

    verts, faces, R, T, _ = template_scene()
    made = MeshRenderer(MeshRasterizer(12, truncate_opaque=True, supersample=3), HardBlend(3))
    expected = build_renderer("hard", image_size=12, supersample=3)
    textures = _tex(2, verts.shape[1])
    torch.testing.assert_close(made(verts, faces, textures, R=R, T=T), expected(verts, faces, textures, R=R, T=T))


@pytest.mark.parametrize("name", list_renderers())
def test_textures_of_other_than_three_channels_take_a_background_color_of_as_many(name):
    verts, faces, R, T, _ = template_scene(batch=1)
    grey = TexturesVertex(torch.full((1, verts.shape[1], 1), 0.25))
    message = "background_color has 3 channels, textures 1: give the renderer 1 background_color values"
    with pytest.raises(ValueError, match=re.escape(message)):
        build_renderer(name, image_size=16)(verts, faces, grey, R=R, T=T)
    out = build_renderer(name, image_size=16, background_color=(0.75,))(verts, faces, grey, R=R, T=T)
    assert out.shape == (1, 2, 16, 16)
    grey_out, alpha = out[:, 0], out[:, 1]
    assert torch.allclose(grey_out[alpha == 0], torch.tensor(0.75))  # the background
    assert torch.allclose(grey_out[alpha == 1], torch.tensor(0.25))  # the mesh
