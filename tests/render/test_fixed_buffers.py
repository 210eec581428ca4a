"""The rasterizer in fixed buffers (:mod:`unicorn.render.fixed`, the renders inside
:func:`unicorn.hostsync.sync_free`): the default fragments, images and gradients, and no host read."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import pytest
import torch

from tests.support.render import posed_ellipsoids
from tests.support.syncs import record_syncs
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.hostsync import sync_free
from unicorn.render import OverflowCounter, RenderOverflowWarning, TexturesVertex, build_renderer
from unicorn.render.raster import blur_radius_from_sigma, rasterize_meshes

#: (blur_radius, faces_per_pixel, truncate_opaque, perspective_correct)
CASES = {
    "hard": (0.0, 1, False, False),
    "blur top-4": (blur_radius_from_sigma(1e-4), 4, False, False),
    "blur top-3 truncated": (blur_radius_from_sigma(1e-4), 3, True, False),
    "perspective top-5": (blur_radius_from_sigma(2e-4), 5, True, True),
}


def _scene(batch: int = 3, dtype=torch.float64):
    verts, faces, R, T = posed_ellipsoids(batch, level=2, dtype=dtype)
    ndc = PerspectiveCamera(fov=30.0).project(verts @ R + T[:, None]).requires_grad_(True)
    return ndc, faces


def _valid(frags):
    keep = frags.valid if frags.valid is not None else torch.ones_like(frags.pix, dtype=torch.bool)
    return {name: getattr(frags, name)[keep] for name in ("pix", "slot", "face", "inside", "bary", "dists", "zbuf")}


@pytest.mark.parametrize("case", CASES)
def test_fixed_buffers_keep_the_default_pairs(case):
    blur, K, truncate, perspective = CASES[case]
    ndc, faces = _scene()
    default = rasterize_meshes(ndc, faces, 24, blur, K, truncate, perspective_correct=perspective)
    P, M = default.sizes.tolist()
    # without the input checks' reads, counting the overflow on the device
    with sync_free(), OverflowCounter() as counter, record_syncs() as rec:
        fixed = rasterize_meshes(
            ndc, faces, 24, blur, K, truncate, perspective_correct=perspective, capacity=(P, M + 7)
        )
    assert not rec.syncs, [str(s) for s in rec.syncs]
    assert counter.take().overflow == default.overflow
    assert fixed.num_pairs == M + 7 and int(fixed.valid.sum()) == M
    assert fixed.sizes.tolist() == [P, M] and int(fixed.overflow) == default.overflow
    a, b = _valid(default), _valid(fixed)
    for name in a:
        assert torch.equal(a[name], b[name]), name
    # the padding: at the last pixel, in the extra slot, transparent
    pad = ~fixed.valid
    assert (fixed.pix[pad] == fixed.pix.max()).all() and (fixed.slot[pad] == K).all()
    assert torch.isinf(fixed.dists[pad]).all() and not fixed.inside[pad].any()
    dense_a, dense_b = default.to_dense(), fixed.to_dense()
    for name in ("pix_to_face", "zbuf", "bary_coords", "dists"):
        assert torch.equal(getattr(dense_a, name), getattr(dense_b, name)[:, :, :, : default.num_slots]), name
    # in PyTorch3D's shapes, K = faces_per_pixel: the same tensors, the padding rows left out
    dense_a, dense_b = default.to_dense(K), fixed.to_dense(K)
    for name in ("pix_to_face", "zbuf", "bary_coords", "dists"):
        assert torch.equal(getattr(dense_a, name), getattr(dense_b, name)), name


def test_fixed_buffers_outside_a_counter_read_no_overflow_back(monkeypatch):
    """Outside any OverflowCounter a warning would read the device's count: inside sync_free it is left in
    Fragments.overflow; outside the block, where reads are allowed, the same render warns."""
    ndc, faces = _scene()
    blur, K = blur_radius_from_sigma(1e-4), 3
    with OverflowCounter():
        default = rasterize_meshes(ndc, faces, 24, blur, K, check_inputs=False)
    assert default.overflow > 0
    monkeypatch.setattr("unicorn.render.overflow._WARNED", set())  # this setting not yet said in this process
    capacity = tuple(default.sizes.tolist())
    with sync_free(), record_syncs() as rec, warnings.catch_warnings():
        warnings.simplefilter("error")
        fixed = rasterize_meshes(ndc, faces, 24, blur, K, check_inputs=False, capacity=capacity)
    assert not rec.syncs, [str(s) for s in rec.syncs]
    assert int(fixed.overflow) == default.overflow
    with pytest.warns(RenderOverflowWarning, match=f"faces_per_pixel={K} "):
        rasterize_meshes(ndc, faces, 24, blur, K, check_inputs=False, capacity=capacity)


def test_fixed_buffers_too_small_drop_pairs_and_say_what_they_needed():
    ndc, faces = _scene()
    default = rasterize_meshes(ndc, faces, 24, blur_radius_from_sigma(1e-4), 4)
    P, M = default.sizes.tolist()
    fixed = rasterize_meshes(ndc, faces, 24, blur_radius_from_sigma(1e-4), 4, capacity=(P, M // 2))
    assert int(fixed.valid.sum()) == M // 2 and fixed.sizes.tolist() == [P, M]
    assert torch.equal(fixed.pix, default.pix[: M // 2])


@pytest.mark.parametrize("kind", ["layered", "softras", "hard"])
def test_fixed_buffer_renders_give_the_default_images_and_gradients(kind):
    verts, faces, R, T = posed_ellipsoids(3, level=2, dtype=torch.float64)
    colors = torch.rand(3, verts.shape[1], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    options = {"hard": {}, "layered": {"sigma": 1e-4, "faces_per_pixel": 6}, "softras": {"faces_per_pixel": 6}}
    renderer = build_renderer(kind, image_size=20, **options[kind])
    out = {}
    for free in (False, True):
        v, c = verts.clone().requires_grad_(True), colors.clone().requires_grad_(True)
        with sync_free(free):
            image = renderer(v, faces, TexturesVertex(c), R=R, T=T)
        (image * torch.linspace(0, 1, image.numel(), dtype=image.dtype).view_as(image)).sum().backward()
        out[free] = (image.detach(), v.grad, c.grad)
    assert renderer.rasterizer.buffers  # sized by the default render, used by the other
    for a, b, name in zip(out[False], out[True], ("image", "verts.grad", "colors.grad")):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12, msg=name)


def test_fixed_buffers_of_nothing_to_draw():
    ndc, faces = _scene()
    for verts, f in ((ndc[:0], faces), (ndc, faces[:0])):
        frags = rasterize_meshes(verts, f, 24, 0.0, 2, capacity=(64, 64))
        assert frags.num_pairs == 0 and frags.overflow == 0


def test_rasterizer_sizes_its_buffers_and_grows_them_when_read():
    verts, faces, R, T = posed_ellipsoids(2, level=2)
    renderer = build_renderer("layered", image_size=16, sigma=1e-4, faces_per_pixel=4)
    rasterizer = renderer.rasterizer
    colors = TexturesVertex(torch.ones(2, verts.shape[1], 3))
    with sync_free():  # no buffers yet for this size: rendered as usual, and they are sized
        renderer(verts, faces, colors, R=R, T=T)
    ((key, (n_cand, n_pairs)),) = rasterizer.buffers.items()
    assert key == (2, 16, 16) and n_cand % 1024 == 0 and n_pairs % 1024 == 0
    rasterizer.buffers[key] = (n_cand, 8)  # too small: the render loses pairs, and says so when read
    with sync_free(), record_syncs() as rec, OverflowCounter():
        renderer(verts, faces, colors, R=R, T=T)
    assert not rec.syncs
    (line,) = rasterizer.grow_buffers()
    assert "lost some" in line and rasterizer.buffers[key] == (n_cand, n_pairs)
    assert rasterizer.grow_buffers() == []  # read once


def test_rasterizer_moved_after_sized_renders_on_its_new_device():
    verts, faces, R, T = posed_ellipsoids(2, level=2)
    renderer = build_renderer("layered", image_size=16, sigma=1e-4, faces_per_pixel=4)
    colors = TexturesVertex(torch.ones(2, verts.shape[1], 3))
    for _ in range(2):  # sizes the buffers, then renders into them: the sizes it needed wait to be read
        with sync_free(), OverflowCounter():
            renderer(verts, faces, colors, R=R, T=T)
    renderer.double()  # a dtype change leaves the integer sizes as they are
    renderer.to("meta")  # the meta device: another device on a machine without GPU
    meta = [t.to("meta", torch.float64) for t in (verts, R, T, colors.colors)]
    with sync_free(), OverflowCounter():
        image = renderer(meta[0], faces.to("meta"), TexturesVertex(meta[3]), R=meta[1], T=meta[2])
    assert image.device.type == "meta" and image.shape == (2, 4, 16, 16)


def test_padding_sends_no_gradient_when_nothing_is_drawn():
    verts, faces, R, T = posed_ellipsoids(2, level=2, dtype=torch.float64)
    renderer = build_renderer("layered", image_size=16, sigma=1e-4, faces_per_pixel=4)
    renderer.rasterizer.buffers[(2, 16, 16)] = (1024, 1024)
    v = verts.clone().requires_grad_(True)
    behind = T * torch.tensor([1.0, 1.0, -1.0], dtype=T.dtype)  # every face behind the camera: nothing to draw
    with sync_free(), OverflowCounter():
        image = renderer(v, faces, TexturesVertex(torch.ones_like(verts)), R=R, T=behind)
    image.sum().backward()
    assert image[:, 3].abs().max() == 0 and torch.equal(v.grad, torch.zeros_like(v))


def test_rasterizer_keeps_the_needed_sizes_on_the_meshes_device(monkeypatch):
    """The first renders of a run size the buffers from sizes read to the host; the fixed renders then fold what they
    needed into a tensor that must be on the meshes' device (a CUDA training run failed on the mix)."""
    import unicorn.render.rasterizer as rasterizer_module

    def fake_rasterize(ndc, faces, size, *args, capacity=None, **kwargs):
        # the default path's sizes are on the host, the fixed buffers' on the device
        if capacity is None:
            return SimpleNamespace(sizes=torch.tensor([300, 200]), valid=None)
        return SimpleNamespace(
            sizes=torch.tensor([310, 190], device=ndc.device), valid=torch.ones(190, device=ndc.device)
        )

    monkeypatch.setattr(rasterizer_module, "rasterize_meshes", fake_rasterize)
    _sized_then_fixed_on_meta(draw_nothing=False)


def _sized_then_fixed_on_meta(draw_nothing: bool) -> None:
    """Render twice on the meta device inside ``sync_free`` (the first render sizes the buffers, the second goes into
    them), then, with ``draw_nothing``, a batch without faces; the sizes the rasterizer keeps stay on that device."""
    verts, faces, R, T = (t.to("meta") for t in posed_ellipsoids(2, level=1))
    rasterizer = build_renderer("layered", image_size=16, sigma=1e-4, faces_per_pixel=4).rasterizer
    with sync_free():
        rasterizer(verts, faces, R, T, check_inputs=False)
        rasterizer(verts, faces, R, T, check_inputs=False)
        if draw_nothing:
            rasterizer(verts, faces[:0], R, T, check_inputs=False)
    (needed,) = rasterizer._needed.values()
    assert needed.device == verts.device


def test_a_mesh_with_nothing_to_draw_renders_inside_sync_free_after_sized_renders(monkeypatch):
    """A batch without faces takes the default path even when the buffers of its size exist (its sizes, on the host,
    are known): the rasterizer must not fold them into the sizes it keeps on the meshes' device (on CUDA the mix is an
    error; the meta device stands for CUDA here)."""
    import unicorn.render.rasterizer as rasterizer_module

    ndc, faces = _scene()
    empty = rasterize_meshes(ndc.detach(), faces[:0], 16, 0.0, 4, capacity=(64, 64))
    assert empty.valid is None and empty.sizes.device.type == "cpu" and empty.sizes.tolist() == [0, 0]

    def fake_rasterize(ndc, faces, size, *args, capacity=None, **kwargs):
        # as rasterize_meshes: the default path (which takes a render with nothing to draw) sizes on the host
        if capacity is None or faces.shape[0] == 0:
            return SimpleNamespace(sizes=torch.tensor([300 * (faces.shape[0] > 0), 0]), valid=None)
        return SimpleNamespace(
            sizes=torch.tensor([310, 190], device=ndc.device), valid=torch.ones(190, device=ndc.device)
        )

    monkeypatch.setattr(rasterizer_module, "rasterize_meshes", fake_rasterize)
    _sized_then_fixed_on_meta(draw_nothing=True)


def test_a_render_under_inference_mode_leaves_the_buffers_usable_for_training():
    """Lightning validates under ``torch.inference_mode``: a render there (a batch size training has not seen) must
    not leave the rasterizer a size tensor that the next steps without host reads, or the read of their sizes, update
    in place outside it (PyTorch refuses in-place updates of inference tensors)."""
    verts, faces, R, T = posed_ellipsoids(2, level=2)
    renderer = build_renderer("layered", image_size=16, sigma=1e-4, faces_per_pixel=4)
    colors = TexturesVertex(torch.ones(2, verts.shape[1], 3))
    with torch.inference_mode(), OverflowCounter():
        expected = renderer(verts, faces, colors, R=R, T=T)  # sizes the buffers of (2, 16, 16)
    assert renderer.rasterizer.grow_buffers() == []  # the read of the sizes, outside inference mode
    with sync_free(), OverflowCounter():  # into the buffers: folds what it needed into the same tensor
        image = renderer(verts, faces, colors, R=R, T=T)
    assert renderer.rasterizer.grow_buffers() == []
    torch.testing.assert_close(image, expected)
