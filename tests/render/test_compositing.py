"""The compositing rules (layered, SoftRas, hard) against naive per-pixel loops from the formulas (float64, Python)."""

import math

import pytest
import torch

from tests.support.render import posed_ellipsoids
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.render import blur_radius_from_sigma, hard_blend, layered_blend, rasterize_meshes, softras_blend

SIZE = 16


@pytest.fixture(scope="module")
def scene():
    """Overlapping ellipsoids at 16 px with a wide blur: many pixels hold several inside and near-miss faces."""
    verts, faces, R, T = posed_ellipsoids(batch=2, level=2, dtype=torch.float64, seed=4)
    ndc = PerspectiveCamera(fov=30.0).transform_points(verts, R, T)
    frags = rasterize_meshes(ndc, faces, SIZE, blur_radius_from_sigma(3e-3), 12)
    g = torch.Generator().manual_seed(0)
    colors = torch.rand(frags.num_pairs, 3, generator=g, dtype=torch.float64)
    bg = torch.rand(2 * SIZE * SIZE, 3, generator=g, dtype=torch.float64)
    assert frags.num_slots > 2 and bool((~frags.inside).any()) and bool(frags.inside.any())
    return frags, colors, bg


def _pairs_by_pixel(frags) -> dict[int, list[int]]:
    """Indices of each pixel's pairs, nearest first."""
    pairs: dict[int, list[int]] = {}
    for i, pixel in enumerate(frags.pix.tolist()):
        pairs.setdefault(pixel, []).append(i)
    return {p: sorted(rows, key=lambda i: int(frags.slot[i])) for p, rows in pairs.items()}


def _pixel(image: torch.Tensor, pixel: int) -> list[float]:
    b, rest = divmod(pixel, SIZE * SIZE)
    y, x = divmod(rest, SIZE)
    return image[b, :, y, x].tolist()


@pytest.mark.parametrize("sigma", [1e-3, 0.0])
def test_layered_blend_matches_a_front_to_back_loop(scene, sigma):
    frags, colors, bg = scene
    out = layered_blend(colors, frags, bg, sigma)
    pairs_of = _pairs_by_pixel(frags)
    for pixel in range(2 * SIZE * SIZE):
        clear, rgb = 1.0, [0.0, 0.0, 0.0]  # light still passing, colour gathered so far
        for i in pairs_of.get(pixel, []):
            if bool(frags.inside[i]):
                occupancy = 1.0
            else:
                occupancy = 0.0 if sigma == 0 else math.exp(-max(float(frags.dists[i]), 0.0) / sigma)
            rgb = [c + clear * occupancy * float(colors[i, k]) for k, c in enumerate(rgb)]
            clear *= 1.0 - occupancy
        expected = [c + clear * float(bg[pixel, k]) for k, c in enumerate(rgb)] + [1.0 - clear]
        # layered_blend caps a near-miss occupancy at 1 - 1e-6 (it sums log(1 - O)): differences up to ~1e-6
        assert _pixel(out, pixel) == pytest.approx(expected, abs=2e-6), pixel


def test_softras_blend_matches_a_softmax_loop(scene):
    frags, colors, bg = scene
    sigma, gamma, znear, zfar, eps = 1e-3, 1e-2, 1.0, 100.0, 1e-3
    out = softras_blend(colors, frags, bg, sigma, gamma, znear, zfar, eps)
    pairs_of = _pairs_by_pixel(frags)
    for pixel in range(2 * SIZE * SIZE):
        pairs = pairs_of.get(pixel, [])
        prob = [1.0 / (1.0 + math.exp(float(frags.dists[i]) / sigma)) for i in pairs]
        z_inv = [(zfar - float(frags.zbuf[i])) / (zfar - znear) for i in pairs]
        # the softmax over the faces and the background layer (D = 1, z_inv = eps), shifted by its largest exponent
        top = max(z_inv + [eps])
        weights = [p * math.exp((z - top) / gamma) for p, z in zip(prob, z_inv)]
        w_bg = math.exp((eps - top) / gamma)
        total = sum(weights) + w_bg
        rgb = [
            (sum(w * float(colors[i, k]) for w, i in zip(weights, pairs)) + w_bg * float(bg[pixel, k])) / total
            for k in range(3)
        ]
        alpha = 1.0 - math.prod(1.0 - p for p in prob)
        assert _pixel(out, pixel) == pytest.approx(rgb + [alpha], abs=1e-9), pixel


@pytest.mark.parametrize("supersample", [1, 2, 4])
def test_hard_blend_matches_a_nearest_face_loop_averaged_over_subpixels(scene, supersample):
    frags, colors, bg_fine = scene
    size = SIZE // supersample
    bg = bg_fine[: 2 * size * size]  # (B * H * W, C) at the output resolution
    out = hard_blend(colors, frags, bg, supersample)
    assert out.shape == (2, 4, size, size)
    pairs_of = _pairs_by_pixel(frags)
    for b in range(2):
        for y in range(size):
            for x in range(size):
                rgb, alpha = [0.0, 0.0, 0.0], 0.0  # means over the subpixels of colour over black and coverage
                for i in range(supersample**2):
                    row, col = supersample * y + i // supersample, supersample * x + i % supersample
                    sub = (b * SIZE + row) * SIZE + col
                    inside = [j for j in pairs_of.get(sub, []) if bool(frags.inside[j])]
                    if inside:  # the nearest face containing the subpixel, near misses ignored
                        rgb = [c + float(colors[inside[0], k]) / supersample**2 for k, c in enumerate(rgb)]
                        alpha += 1.0 / supersample**2
                pixel = (b * size + y) * size + x
                expected = [c + (1.0 - alpha) * float(bg[pixel, k]) for k, c in enumerate(rgb)] + [alpha]
                assert out[b, :, y, x].tolist() == pytest.approx(expected, abs=1e-12), (b, y, x)


def test_hard_blend_needs_the_background_at_the_supersampled_size(scene):
    frags, colors, bg = scene
    with pytest.raises(ValueError, match=r"^bg_table must have shape \(128, 3\), got \(512, 3\)$"):
        hard_blend(colors, frags, bg, supersample=2)  # 2 images of 8 x 8 pixels at supersample 2
    with pytest.raises(ValueError, match="not a supersampling by 3"):
        hard_blend(colors, frags, bg[: 2 * 5 * 5], supersample=3)


@pytest.mark.parametrize(
    "blend", [lambda *a: layered_blend(*a, sigma=1e-4), hard_blend, softras_blend], ids=["layered", "hard", "softras"]
)
def test_a_blend_names_the_argument_of_the_wrong_shape(scene, blend):
    frags, colors, bg = scene
    M = frags.num_pairs
    for args, message in [
        ((colors[:-1], frags, bg), rf"^colors must have shape \({M}, C\), got \({M - 1}, 3\)$"),
        ((colors[:, 0], frags, bg), rf"^colors must have shape \({M}, C\), got \({M},\)$"),
        ((colors, frags, bg[:-1]), r"^bg_table must have shape \(512, 3\), got \(511, 3\)$"),
        ((colors, frags, bg[:, :2]), r"^bg_table must have shape \(512, 3\), got \(512, 2\)$"),
    ]:
        with pytest.raises(ValueError, match=message):
            blend(*args)
    for args, message in [
        ((colors.float(), frags, bg), r"^colors is torch.float32 but fragments.bary is torch.float64: give both the"),
        ((colors, frags, bg.float()), r"^bg_table is torch.float32 but fragments.bary is torch.float64: give both"),
    ]:
        with pytest.raises(TypeError, match=message):  # blends add colours and weights: no silent promotion
            blend(*args)
