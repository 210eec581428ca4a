"""The contract every registered backend honours, and the registry itself."""

import pytest
import torch

from tests.support.render import template_scene
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.registry import UnknownNameError, UnknownOptionError
from unicorn.render import (
    HardBlend,
    LayeredBlend,
    LayeredRasterizer,
    MeshRasterizer,
    MeshRenderer,
    SoftRasBlend,
    TexturesUV,
    TexturesVertex,
    blur_radius_from_sigma,
    build_renderer,
    get_renderer_class,
    list_renderers,
    register_renderer,
    unregister_renderer,
)


@register_renderer("test-flat")
class FlatRenderer(MeshRenderer):
    """A third-party backend: hard edges, colour of the nearest face, composed from the public pieces."""

    position_gradients = False

    def __init__(self, image_size=64, camera=None, background_color=(1.0, 1.0, 1.0)):
        rasterizer = MeshRasterizer(image_size, 1, 0.0, camera, truncate_opaque=True)
        super().__init__(rasterizer, LayeredBlend(sigma=0.0), background_color)


def test_registry_round_trip_and_third_party_backend():
    names = list_renderers()
    assert {"layered", "softras", "hard", "test-flat"} <= set(names)
    assert get_renderer_class("layered") is LayeredRasterizer
    assert isinstance(build_renderer("test-flat", image_size=16), FlatRenderer)
    with pytest.raises(ValueError, match="already registered"):
        register_renderer("layered")(FlatRenderer)
    with pytest.raises(UnknownNameError, match=r"unknown renderer 'nope'; known: \[.*'layered'"):
        build_renderer("nope")
    with pytest.raises(UnknownNameError, match=r"unknown renderer 'nope'"):
        get_renderer_class("nope")
    with pytest.raises(UnknownOptionError, match="renderer 'layered' takes no option 'sigmaa'"):
        build_renderer("layered", sigmaa=1.0)
    with pytest.raises(TypeError, match="must be a subclass of Module"):
        register_renderer("broken")(object)
    register_renderer("tmp")(FlatRenderer)
    unregister_renderer("tmp")
    assert "tmp" not in list_renderers()


def test_hydra_configs_exist_for_builtin_backends():
    """Each built-in backend has ``conf/renderer/<name>.yaml`` naming it by its registry name, and the file's
    other options (its camera aside) build that backend through the registry."""
    from pathlib import Path

    import yaml

    conf = Path(__file__).resolve().parents[2] / "conf" / "renderer"
    for name in ("layered", "softras", "hard"):
        cfg = yaml.safe_load((conf / f"{name}.yaml").read_text())
        assert cfg.pop("name") == name and "_target_" not in cfg
        cfg.pop("camera", None)
        assert type(build_renderer(name, **cfg)) is get_renderer_class(name)


@pytest.fixture(params=list_renderers())
def renderer_name(request):
    return request.param


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_output_shape_range_dtype(renderer_name, dtype):
    verts, faces, R, T, uvs = template_scene(batch=3, dtype=dtype)
    renderer = build_renderer(renderer_name, image_size=32).to(dtype)
    maps = torch.rand(3, 3, 16, 16, dtype=dtype)
    images = renderer(verts, faces, TexturesUV(maps, uvs), R=R, T=T)
    assert images.shape == (3, 4, 32, 32) and images.dtype == dtype
    assert torch.isfinite(images).all()
    assert images.min() >= 0 and images.max() <= 1 + 1e-6
    alpha = images[:, 3]
    assert (
        alpha[:, 0, 0].max() == 0 and alpha[:, 16, 16].min() > 0.9
    )  # corner empty, centre covered (SoftRas is softer inside)
    # where nothing is drawn, the image is the background colour
    empty = alpha == 0
    assert torch.allclose(images[:, :3].permute(0, 2, 3, 1)[empty], torch.ones(1, 3, dtype=dtype))


def test_background_image_and_colour(renderer_name):
    verts, faces, R, T, uvs = template_scene(batch=2)
    renderer = build_renderer(renderer_name, image_size=24, background_color=(0.0, 0.5, 1.0))
    tex = TexturesVertex(torch.rand(2, verts.shape[1], 3))
    images = renderer(verts, faces, tex, R=R, T=T)
    assert torch.allclose(images[:, :3, 0, 0], torch.tensor([[0.0, 0.5, 1.0]] * 2))
    bg = torch.rand(2, 3, 24, 24)
    images = renderer(verts, faces, tex, R=R, T=T, background=bg)
    assert torch.allclose(images[:, :3, 0, 0], bg[:, :, 0, 0])
    with pytest.raises(ValueError, match=r"background must have shape \(2, 3, 24, 24\)"):
        renderer(verts, faces, tex, R=R, T=T, background=torch.rand(2, 3, 12, 12))


def test_render_output_depth_and_face_ids(renderer_name):
    verts, faces, R, T, _ = template_scene(batch=2)
    renderer = build_renderer(renderer_name, image_size=32)
    out = renderer.render(verts, faces, TexturesVertex(torch.rand(2, verts.shape[1], 3)), R=R, T=T)
    ids, depth = out.face_ids, out.depth
    assert ids.dtype == torch.long and ids.min() >= -1 and ids.max() < faces.shape[0]
    covered = ids >= 0
    assert (depth[:, 0][covered] > 2.0).all() and (depth[:, 0][covered] < 3.5).all()
    assert (depth[:, 0][~covered] == 0).all()


def test_batch_of_192_and_level_4_mesh(renderer_name):
    from unicorn.geometry.mesh import ellipsoid, spherical_face_uvs
    from unicorn.geometry.rotations import look_at_view_transform

    v, f = ellipsoid(4, scale=0.6)
    B = 192
    R, T = look_at_view_transform(2.732, 10.0, torch.linspace(0, 360, B))
    maps = torch.rand(B, 3, 8, 8, generator=torch.Generator().manual_seed(0))  # a texture of its own per image
    uvs = spherical_face_uvs(v, f)
    renderer = build_renderer(renderer_name, image_size=32)
    renderer.rasterizer.max_candidates = 1 << 19  # ~12k candidates an image: the batch is rasterized in chunks
    images = renderer(v[None].expand(B, -1, -1), f, TexturesUV(maps, uvs), R=R, T=T)
    assert images.shape == (B, 4, 32, 32)
    assert (images[:, 3].sum(dim=(1, 2)) > 100).all()  # every view covers the image's centre
    # each image as the same mesh, pose and texture rendered alone (every 4th: each chunk is sampled)
    for b in range(0, B, 4):
        alone = renderer(v[None], f, TexturesUV(maps[b : b + 1], uvs), R=R[b : b + 1], T=T[b : b + 1])
        torch.testing.assert_close(images[b : b + 1], alone, atol=1e-6, rtol=1e-5, msg=f"image {b}")


@pytest.mark.gpu
def test_cuda_matches_cpu(renderer_name):
    verts, faces, R, T, uvs = template_scene(batch=2)
    maps = torch.rand(2, 3, 16, 16)
    cpu = build_renderer(renderer_name, image_size=32)
    gpu = build_renderer(renderer_name, image_size=32).cuda()
    a = cpu(verts, faces, TexturesUV(maps, uvs), R=R, T=T)
    b = gpu(verts.cuda(), faces.cuda(), TexturesUV(maps.cuda(), uvs.cuda()), R=R.cuda(), T=T.cuda())
    assert torch.allclose(a, b.cpu(), atol=1e-4)


def test_camera_is_configurable(renderer_name):
    verts, faces, R, T, _ = template_scene(batch=1)
    tex = TexturesVertex(torch.rand(1, verts.shape[1], 3))
    wide = build_renderer(renderer_name, image_size=32, camera=PerspectiveCamera(fov=60.0))(verts, faces, tex, R=R, T=T)
    narrow = build_renderer(renderer_name, image_size=32, camera=PerspectiveCamera(fov=30.0))(
        verts, faces, tex, R=R, T=T
    )
    assert wide[:, 3].sum() < 0.5 * narrow[:, 3].sum()


# the built-in backends' options in the test below, and the same renderers composed by hand
_OPTIONS = {
    "layered": {"sigma": 1e-3, "faces_per_pixel": 25},
    "softras": {"sigma": 1e-3, "gamma": 1e-2, "faces_per_pixel": 40, "znear": 0.5},
    "hard": {"supersample": 2},
}
_BY_HAND = {
    "layered": lambda cam: MeshRenderer(
        MeshRasterizer(16, 25, blur_radius_from_sigma(1e-3), cam, truncate_opaque=True), LayeredBlend(1e-3)
    ),
    "softras": lambda cam: MeshRenderer(
        MeshRasterizer(16, 40, blur_radius_from_sigma(1e-3), cam), SoftRasBlend(1e-3, 1e-2, 0.5, cam.zfar, 1e-3)
    ),
    "hard": lambda cam: MeshRenderer(
        MeshRasterizer(16, 1, 0.0, cam, truncate_opaque=True, supersample=2), HardBlend(2)
    ),
}


def _images_and_gradients(render, verts, faces, maps, uvs, R, T, bg):
    """Images (B, 4, 16, 16) and the gradients of a weighted sum to the vertices, texture maps and background."""
    inputs = [x.detach().clone().requires_grad_() for x in (verts, maps, bg)]
    images = render(inputs[0], faces, TexturesUV(inputs[1], uvs), R, T, inputs[2])
    weights = torch.rand(images.shape, generator=torch.Generator().manual_seed(1), dtype=images.dtype)
    return [images, *torch.autograd.grad((images * weights).sum(), inputs, allow_unused=True)]


def test_registered_renderer_is_its_rasterizer_then_its_aggregator(renderer_name):
    assert {"layered", "softras", "hard"} <= set(_BY_HAND)
    verts, faces, R, T, uvs = template_scene(batch=2, level=2, dtype=torch.float64)
    verts = verts + 0.02 * torch.randn(verts.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    g = torch.Generator().manual_seed(2)
    maps, bg = torch.rand(2, 3, 8, 8, generator=g, dtype=torch.float64), torch.rand(2, 3, 16, 16, generator=g)
    camera = PerspectiveCamera(fov=35.0)
    renderer = build_renderer(renderer_name, image_size=16, camera=camera, **_OPTIONS.get(renderer_name, {})).double()
    bg = bg.double()

    def by_parts(verts, faces, textures, R, T, bg):
        fragments = renderer.rasterizer(verts, faces, R, T)
        table = bg.permute(0, 2, 3, 1).reshape(-1, bg.shape[1])
        return renderer.blend(textures.sample(fragments, faces), fragments, table)

    expected = _images_and_gradients(renderer.forward, verts, faces, maps, uvs, R, T, bg)
    composed = [by_parts]
    if renderer_name in _BY_HAND:
        composed.append(_BY_HAND[renderer_name](camera).double().forward)
    for render in composed:
        for want, got in zip(expected, _images_and_gradients(render, verts, faces, maps, uvs, R, T, bg)):
            assert (want is None and got is None) or torch.equal(want, got)
