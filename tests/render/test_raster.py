"""Rasterizer against independent oracles: open3d ray casting and a brute-force per-pixel loop."""

import math
import warnings

import numpy as np
import pytest
import torch
import trimesh

from tests.support.render import posed_ellipsoids, random_rotations
from unicorn.geometry.cameras import PerspectiveCamera, pixel_to_ndc, world_to_view
from unicorn.render import Fragments, blur_radius_from_sigma, rasterize_meshes


def _raycast(view_verts: np.ndarray, faces: np.ndarray, focal: float, size: int):
    """First hit of the ray through every pixel centre: face id (-1 none), depth, barycentrics."""
    import open3d as o3d  # imported where used: the gpu tests run where open3d is not installed

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(view_verts.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    cols, rows = np.meshgrid(np.arange(size), np.arange(size))
    ndc = pixel_to_ndc(torch.tensor(np.stack([cols, rows], -1), dtype=torch.float64), size).numpy()
    dirs = np.concatenate([ndc / focal, np.ones((size, size, 1))], -1)
    rays = np.concatenate([np.zeros_like(dirs), dirs], -1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    ids = hit["primitive_ids"].numpy().astype(np.int64)
    ids[~np.isfinite(t)] = -1
    uv = hit["primitive_uvs"].numpy()
    bary = np.stack([1 - uv[..., 0] - uv[..., 1], uv[..., 0], uv[..., 1]], -1)
    return ids, t, bary  # with unit z direction, t is the view depth


def _scenes():
    verts, faces, R, T = posed_ellipsoids(batch=3, level=3)
    yield verts, faces, R, T
    g = torch.Generator().manual_seed(3)
    for mesh in (trimesh.creation.torus(0.5, 0.2), trimesh.creation.box((0.9, 0.5, 0.7))):
        if len(mesh.faces) < 200:
            mesh = mesh.subdivide().subdivide()
        v = torch.tensor(mesh.vertices, dtype=torch.float32)[None].repeat(2, 1, 1) @ random_rotations(2, g)
        Rs = torch.eye(3).repeat(2, 1, 1)
        Ts = torch.tensor([[0.05, -0.1, 2.5], [-0.1, 0.0, 3.0]])
        yield v, torch.tensor(mesh.faces), Rs, Ts


@pytest.mark.parametrize("scene", list(_scenes()), ids=["ellipsoids", "torus", "box"])
def test_first_layer_matches_open3d_ray_casting(scene):
    verts, faces, R, T = scene
    size, cam = 48, PerspectiveCamera(fov=30.0)
    view = world_to_view(verts, R, T)
    frags = rasterize_meshes(cam.project(view), faces, size, blur_radius_from_sigma(1e-4), 25, truncate_opaque=True)
    face_ids, depth = frags.first_layer()
    for b in range(verts.shape[0]):
        ids, t, bary = _raycast(view[b].numpy(), faces.numpy(), float(cam.focal_length), size)
        # away from edges: the ray hits its face well inside (barycentrics > 0.02)
        interior = (ids >= 0) & (bary.min(-1) > 0.02)
        assert interior.sum() > 50
        assert np.array_equal(face_ids[b].numpy()[interior], ids[interior])
        # our depth interpolates z linearly in screen space (no perspective correction, as the reference)
        assert np.allclose(depth[b].numpy()[interior], t[interior], rtol=2e-3)
        # background agrees too, away from silhouettes: where the ray and the rays of the 8 neighbouring pixels
        # all miss, the nearest face is over a pixel away, beyond the blur radius (~0.7 px here)
        miss = np.pad(ids < 0, 1, constant_values=True)
        far = np.all(
            [miss[1 + dy : 1 + dy + size, 1 + dx : 1 + dx + size] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 0
        )
        assert far.sum() > 50
        assert (face_ids[b].numpy()[far] < 0).all()


def _brute_force(verts_ndc: np.ndarray, faces: np.ndarray, size: int, blur: float, K: int):
    """Per-pixel loop over every face, written independently of the rasterizer (numpy, float64)."""
    B = verts_ndc.shape[0]
    cols, rows = np.meshgrid(np.arange(size), np.arange(size))
    centres = np.stack([1 - (2 * cols + 1) / size, 1 - (2 * rows + 1) / size], -1).reshape(-1, 2)
    result = []
    for b in range(B):
        per_pixel = [[] for _ in range(size * size)]
        for fi, (i0, i1, i2) in enumerate(faces):
            a, bb, c = verts_ndc[b, i0], verts_ndc[b, i1], verts_ndc[b, i2]
            if min(a[2], bb[2], c[2]) <= 0:
                continue
            area = 0.5 * ((bb[0] - a[0]) * (c[1] - a[1]) - (bb[1] - a[1]) * (c[0] - a[0]))
            if abs(area) <= 1e-8:
                continue
            p = centres

            # barycentrics by sub-triangle areas (signed)
            def sub(u, v, p=p):
                return 0.5 * ((v[0] - u[0]) * (p[:, 1] - u[1]) - (v[1] - u[1]) * (p[:, 0] - u[0]))

            w = np.stack([sub(bb[:2], c[:2]), sub(c[:2], a[:2]), sub(a[:2], bb[:2])], -1) / area
            inside = (w > 0).all(-1)
            d2 = np.full(len(p), np.inf)
            for u, v in ((a, bb), (bb, c), (c, a)):
                e = v[:2] - u[:2]
                t = np.clip(((p - u[:2]) @ e) / (e @ e), 0, 1)
                d2 = np.minimum(d2, ((p - (u[:2] + t[:, None] * e)) ** 2).sum(-1))
            wc = np.clip(w, 0, None)
            wc = wc / np.maximum(wc.sum(-1, keepdims=True), 1e-5)
            z = wc @ np.array([a[2], bb[2], c[2]])
            for pi in np.nonzero(inside | (d2 < blur))[0]:
                per_pixel[pi].append((z[pi], fi, -d2[pi] if inside[pi] else d2[pi], tuple(wc[pi])))
        result.append([sorted(cands)[:K] for cands in per_pixel])
    return result


def test_dense_fragments_in_pytorch3d_shapes_pad_the_slots_no_pixel_filled():
    verts, faces, R, T = posed_ellipsoids(batch=2, level=1, dtype=torch.float64, seed=1)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    frags = rasterize_meshes(ndc, faces, 12, blur_radius_from_sigma(5e-4), 25)
    K = frags.num_slots
    assert 1 < K < 25
    kept, padded = frags.to_dense(), frags.to_dense(25)
    for name in ("pix_to_face", "zbuf", "bary_coords", "dists"):
        got, want = getattr(padded, name), getattr(kept, name)
        assert got.shape[3] == 25 and torch.equal(got[:, :, :, :K], want), name
        assert (got[:, :, :, K:] == -1).all(), name
    with pytest.raises(ValueError, match=f"faces_per_pixel=1 is below the {K} faces a pixel kept"):
        frags.to_dense(1)
    for bad in (K + 0.5, True, float("nan"), 0):
        with pytest.raises(ValueError, match="faces_per_pixel must be a whole number >= 1, got"):
            frags.to_dense(bad)
    assert torch.equal(frags.to_dense(25.0).pix_to_face, padded.pix_to_face)  # 25.0 is 25


@pytest.mark.parametrize("K", [1, 4, 25])
def test_fragments_match_brute_force(K):
    verts, faces, R, T = posed_ellipsoids(batch=2, level=1, dtype=torch.float64, seed=1)
    size, blur = 20, blur_radius_from_sigma(5e-4)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    frags = rasterize_meshes(ndc, faces, size, blur, K)
    dense = frags.to_dense()
    expected = _brute_force(ndc.numpy(), faces.numpy(), size, blur, K)
    for b in range(2):
        for pi in range(size * size):
            r, c = divmod(pi, size)
            exp = expected[b][pi]
            got = dense.pix_to_face[b, r, c].tolist()
            assert got[: len(exp)] == [e[1] for e in exp], (b, r, c)
            assert all(g == -1 for g in got[len(exp) :])
            for k, (z, _, d, w) in enumerate(exp):
                assert dense.zbuf[b, r, c, k].item() == pytest.approx(z, abs=1e-9)
                assert dense.dists[b, r, c, k].item() == pytest.approx(d, abs=1e-12)
                assert dense.bary_coords[b, r, c, k].tolist() == pytest.approx(w, abs=1e-9)
    assert frags.num_slots <= K


@pytest.mark.parametrize("K", [2, 4])
def test_overflow_counts_the_pixels_with_too_many_faces(K, monkeypatch):
    from unicorn.render import RenderOverflowWarning, overflow

    verts, faces, R, T = posed_ellipsoids(batch=2, level=1, dtype=torch.float64, seed=1)
    size, blur = 20, blur_radius_from_sigma(5e-4)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    every = _brute_force(ndc.numpy(), faces.numpy(), size, blur, K=10**9)  # every candidate of every pixel
    expected = sum(len(cands) > K for image in every for cands in image)
    assert expected > 0
    monkeypatch.setattr(overflow, "_WARNED", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for _ in range(3):
            frags = rasterize_meshes(ndc, faces, size, blur, K)
            assert frags.overflow == expected
            warnings.filterwarnings("ignore", message="unrelated")  # as Lightning does, which resets the registry
    # reported once per setting and process, however often the filters change, with the render's share
    assert [str(w.message).count(f"faces_per_pixel={K} ") for w in caught] == [1]
    assert caught[0].category is RenderOverflowWarning and caught[0].filename == __file__
    assert f"{100 * expected / (2 * size * size):.2g}% of this render's {2 * size * size} pixels" in str(
        caught[0].message
    )


def test_an_overflow_counter_collects_the_renders_without_warning(monkeypatch):
    from unicorn.render import OverflowCounter, overflow

    verts, faces, R, T = posed_ellipsoids(batch=2, level=1, dtype=torch.float64, seed=1)
    size, blur, K = 20, blur_radius_from_sigma(5e-4), 2
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    every = _brute_force(ndc.numpy(), faces.numpy(), size, blur, K=10**9)
    expected = sum(len(cands) > K for image in every for cands in image)
    monkeypatch.setattr(overflow, "_WARNED", set())
    outer, inner = OverflowCounter(), OverflowCounter()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails
        with outer:
            rasterize_meshes(ndc, faces, size, blur, K)
            with inner:  # the innermost active counter takes the render
                rasterize_meshes(ndc[:1], faces, size, blur, K + 1)
            rasterize_meshes(ndc, faces, size, blur, 1000)  # nothing overflows: pixels only
    assert (outer.overflow, outer.pixels, outer.faces_per_pixel) == (expected, 4 * size * size, K)
    # the share is over the renders with the setting that overflowed: the others do not dilute it
    assert outer.counts == {K: (expected, 2 * size * size), 1000: (0, 2 * size * size)}
    assert outer.share == expected / (2 * size * size)
    assert inner.pixels == size * size and inner.faces_per_pixel == (K + 1 if inner.overflow else 0)
    assert outer.describe().startswith(f"{100 * outer.share:.2g}% of the 800 pixels rendered with faces_per_pixel={K}")
    counts = outer.take()
    assert counts.overflow == expected and outer == OverflowCounter() and math.isnan(outer.share)
    outer.stop()  # not active: nothing happens
    with pytest.warns(overflow.RenderOverflowWarning):  # no counter active any more: the warning is back
        rasterize_meshes(ndc, faces, size, blur, K)


def test_a_renders_overflow_warning_points_at_the_line_that_asked_for_it_and_not_for_one_face_per_pixel(monkeypatch):
    from unicorn.render import LayeredRenderer, TexturesVertex, overflow

    verts, faces, R, T = posed_ellipsoids(batch=1, level=2)
    textures = TexturesVertex(torch.rand(1, verts.shape[1], 3))
    monkeypatch.setattr(overflow, "_WARNED", set())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a closed mesh overflows one face per pixel: what K = 1 asks for
        LayeredRenderer(image_size=24, faces_per_pixel=1)(verts, faces, textures, R=R, T=T)
    with pytest.warns(overflow.RenderOverflowWarning) as caught:
        LayeredRenderer(image_size=24, faces_per_pixel=2)(verts, faces, textures, R=R, T=T)
    assert caught[0].filename == __file__  # through the renderer, its rasterizer and nn.Module's calls


def test_opaque_truncation_is_exact():
    from unicorn.render import layered_blend

    verts, faces, R, T = posed_ellipsoids(batch=3, level=3)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    blur = blur_radius_from_sigma(1e-4)
    colors_of = lambda fr: torch.sin(fr.face.float())[:, None].repeat(1, 3)  # noqa: E731
    bg = torch.ones(3 * 64 * 64, 3)
    full = rasterize_meshes(ndc, faces, 64, blur, 50)
    cut = rasterize_meshes(ndc, faces, 64, blur, 50, truncate_opaque=True)
    assert cut.num_pairs < full.num_pairs
    assert torch.equal(layered_blend(colors_of(full), full, bg, 1e-4), layered_blend(colors_of(cut), cut, bg, 1e-4))


@pytest.mark.parametrize("capacity", [None, (1 << 15, 1 << 12)], ids=["packed", "fixed"])
@pytest.mark.parametrize("K", [1, 2, 3])
def test_opaque_truncation_keeps_the_nearest_containing_face(K, capacity):
    """Near misses in front of a pixel's nearest containing face give way to it: with more than K - 1 of them, the
    K - 1 nearest and that face are kept (the brute-force candidates, cut after it)."""
    verts, faces, R, T = posed_ellipsoids(batch=2, level=1, dtype=torch.float64, seed=1)
    size, blur = 20, blur_radius_from_sigma(5e-4)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    dense = rasterize_meshes(ndc, faces, size, blur, K, truncate_opaque=True, capacity=capacity).to_dense()
    every = _brute_force(ndc.numpy(), faces.numpy(), size, blur, len(faces))
    given_way = 0
    for b in range(2):
        for pi in range(size * size):
            r, c = divmod(pi, size)
            cands = every[b][pi]
            first = next((i for i, (_, _, d, _) in enumerate(cands) if d < 0), None)
            if first is None:
                want = cands[:K]
            else:
                want = cands[: first + 1] if first < K else [*cands[: K - 1], cands[first]]
                given_way += first >= K
            got = dense.pix_to_face[b, r, c].tolist()
            assert got[: len(want)] == [f for _, f, _, _ in want] and all(g == -1 for g in got[len(want) :]), (b, r, c)
    if K == 1:
        assert given_way > 0  # the case arises


def _grid_on_pixel_centres(size: int, n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, int]:
    """A flat n x n grid of squares at depth 2, its vertices on the pixel centres of every third column and row from
    the third (``pixel_to_ndc``), each square split along one of its diagonals in turn and every other face wound
    the other way: (1, V, 3) NDC vertices, (F, 3) faces, and the grid's last pixel column (and row)."""
    idx = torch.arange(n + 1) * 3 + 2
    cols, rows = torch.meshgrid(idx, idx, indexing="xy")
    ndc = pixel_to_ndc(torch.stack([cols, rows], -1).to(dtype), size).reshape(-1, 2)
    verts = torch.cat([ndc, torch.full_like(ndc[:, :1], 2.0)], -1)[None]
    faces = []
    for r in range(n):
        for c in range(n):
            a, b, d, e = r * (n + 1) + c, r * (n + 1) + c + 1, (r + 1) * (n + 1) + c, (r + 1) * (n + 1) + c + 1
            pair = [[a, b, e], [a, e, d]] if (r + c) % 2 else [[a, b, d], [b, e, d]]
            faces += [pair[0], pair[1][::-1] if c % 2 else pair[1]]
    return verts, torch.tensor(faces), int(idx[-1])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("capacity", [None, (4096, 4096)], ids=["packed", "fixed"])
def test_a_pixel_centre_on_shared_edges_is_covered_by_exactly_one_face(dtype, capacity):
    size = 40
    verts, faces, last = _grid_on_pixel_centres(size, 10, dtype)
    frags = rasterize_meshes(verts, faces, size, 0.0, 8, capacity=capacity)
    covered = torch.bincount(frags.pix[frags.inside], minlength=size * size).reshape(size, size)
    # the grid tiles the square between the centres of pixels 2 and `last`: every centre strictly within it lies in
    # exactly one face, those on its edges, at its corners and along the shared edges and vertices included
    assert torch.equal(covered[3:last, 3:last], torch.ones(last - 3, last - 3, dtype=covered.dtype))
    assert int(covered.max()) == 1 and int(covered[:2].sum() + covered[:, :2].sum()) == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("capacity", [None, (4096, 4096)], ids=["packed", "fixed"])
def test_a_fan_centred_on_a_pixel_centre_covers_it_once(dtype, capacity):
    # the centre vertex on the optical axis sits on the middle pixel's centre of an odd image (a cone's apex, a
    # sphere's pole): every edge through it must pass exactly through it, whatever its slope
    holes, doubles = [], []
    for n in range(3, 33):
        angles = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n + 0.1 * n
        rim = torch.stack([0.4 * angles.cos(), 0.4 * angles.sin(), torch.full_like(angles, 3.0)], 1)
        verts = torch.cat([torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64), rim]).to(dtype)[None]
        faces = torch.tensor([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
        for size in (1, 3, 9, 15):
            frags = rasterize_meshes(verts, faces, size, 0.0, 8, capacity=capacity)
            covered = torch.bincount(frags.pix[frags.inside], minlength=size * size)
            centre = (size // 2) * size + size // 2
            holes += [(n, size)] if int(covered[centre]) == 0 else []
            doubles += [(n, size)] if int(covered.max()) > 1 else []
    assert holes == [] and doubles == []


@pytest.mark.parametrize("capacity", [None, (512, 512)], ids=["packed", "fixed"])
def test_the_depth_order_of_a_pixel_does_not_depend_on_the_other_images(capacity):
    # two faces 1e-4 apart in image 0; image 1 holds a face a million units away, which stretches the batch's depths
    near, far = [[-0.5, -0.5], [0.5, -0.5], [0.0, 0.5]], [[-0.6, -0.4], [0.6, -0.4], [0.0, 0.6]]
    verts = torch.tensor([[[*xy, 3.0] for xy in far] + [[*xy, 2.9999] for xy in near]])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    alone = rasterize_meshes(verts, faces, 9, 0.0, 2, capacity=capacity).first_layer()[0]
    batch = torch.cat([verts, verts * torch.tensor([1.0, 1.0, 1e6 / 3])])
    together = rasterize_meshes(batch, faces, 9, 0.0, 2, capacity=capacity).first_layer()[0]
    assert int(alone[0, 4, 4]) == 1 and torch.equal(together[:1], alone)


def test_chunking_does_not_change_fragments():
    verts, faces, R, T = posed_ellipsoids(batch=5, level=2)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    one = rasterize_meshes(ndc, faces, 32, 1e-3, 10)
    many = rasterize_meshes(ndc, faces, 32, 1e-3, 10, max_candidates=1)
    for name in ("pix", "slot", "face", "inside"):
        assert torch.equal(getattr(one, name), getattr(many, name))
    assert torch.equal(one.dists, many.dists)


def test_packed_layout_invariants():
    verts, faces, R, T = posed_ellipsoids(batch=2, level=2)
    frags = rasterize_meshes(PerspectiveCamera(fov=30.0).transform_points(verts, R, T), faces, 32, 1e-3, 8)
    assert isinstance(frags, Fragments)
    assert (frags.pix[1:] >= frags.pix[:-1]).all()
    same = frags.pix[1:] == frags.pix[:-1]
    assert (frags.slot[1:][same] == frags.slot[:-1][same] + 1).all()
    assert (frags.zbuf[1:][same] >= frags.zbuf[:-1][same] - 1e-6).all()
    assert torch.allclose(frags.bary.sum(-1), torch.ones(frags.num_pairs))
    assert (frags.bary >= 0).all()
    assert ((frags.dists < 0) == frags.inside).all()


def test_faces_behind_camera_and_degenerate_faces_are_skipped():
    # a triangle crossing z = 0, a zero-area triangle and one good triangle
    verts = torch.tensor(
        [
            [
                [0.0, 0.0, -1.0],
                [0.5, 0.0, 2.0],
                [0.0, 0.5, 2.0],
                [0.1, 0.1, 2.0],
                [0.1, 0.1, 2.0],
                [0.2, 0.2, 2.0],
                [0.0, 0.0, 3.0],
                [-0.3, 0.0, 3.0],
                [0.0, -0.3, 3.0],
            ]
        ],
        requires_grad=True,
    )
    faces = torch.arange(9).view(3, 3)
    frags = rasterize_meshes(PerspectiveCamera(fov=60.0).project(verts), faces, 16, 1e-3, 5)
    assert set(frags.face.tolist()) == {2}
    frags.dists.sum().backward()
    assert torch.isfinite(verts.grad).all()


def test_near_miss_distance_in_ndc_units():
    # a huge triangle covering x_ndc >= 0.03 (image left of a vertical edge); near misses lie to its right
    size, edge = 16, 0.03
    verts = torch.tensor([[[edge, -5.0, 1.0], [edge, 5.0, 1.0], [edge + 10.0, 0.0, 1.0]]], dtype=torch.float64)
    blur = (3 * 2.0 / size) ** 2  # three pixels
    frags = rasterize_meshes(verts, torch.tensor([[0, 1, 2]]), size, blur_radius=blur, faces_per_pixel=1)
    x_centre = 1 - (2 * (frags.pix % size).double() + 1) / size
    assert torch.equal(frags.inside, x_centre > edge)
    expected = (x_centre - edge) ** 2
    assert torch.allclose(frags.dists.abs(), expected)
    assert (expected[~frags.inside] < blur).all()
    # every pixel within the radius is there: 16 rows x (covered columns + 3 near-miss columns)
    assert frags.num_pairs == size * int(((1 - (2 * torch.arange(size) + 1) / size) > edge - 3 * 2.0 / size).sum())


def test_a_whole_float_number_of_faces_per_pixel_gives_the_fragments_of_that_integer():
    verts, faces, R, T = posed_ellipsoids(batch=1, level=2)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    for truncate in (False, True):
        whole = rasterize_meshes(ndc, faces, 16, 1e-3, 2, truncate_opaque=truncate)
        given_as_float = rasterize_meshes(ndc, faces, 16, 1e-3, 2.0, truncate_opaque=truncate, max_candidates=1e6)
        assert given_as_float.slot.dtype == torch.int64 and type(given_as_float.num_slots) is int
        assert torch.equal(given_as_float.slot, whole.slot) and torch.equal(given_as_float.pix, whole.pix)
        assert given_as_float.to_dense().zbuf.shape == whole.to_dense().zbuf.shape
