"""The mean shape of a set of shapes (:func:`unicorn.evaluation.mean_shape.fit_mean_shape`)."""

from __future__ import annotations

import pytest
import torch
import trimesh

from unicorn.evaluation.mean_shape import _sample_chamfer, fit_mean_shape
from unicorn.geometry.mesh import ellipsoid
from unicorn.metrics import NearestNeighborIndex, chamfer_l1, sample_points_from_meshes

# a 162-vertex template, UNICORN's ShapeNet ellipsoid at level 2
TEMPLATE_VERTS, TEMPLATE_FACES = ellipsoid(2, (1.0, 0.7, 0.7), 0.4)


def _surface_points(mesh: trimesh.Trimesh, n: int, seed: int) -> torch.Tensor:
    verts = torch.tensor(mesh.vertices, dtype=torch.float32)
    return sample_points_from_meshes(verts, torch.tensor(mesh.faces), n, seed=seed)[0]


def _mesh_points(verts: torch.Tensor, n: int = 10_000) -> torch.Tensor:
    return sample_points_from_meshes(verts, TEMPLATE_FACES, n, seed=5)[0]


def _chamfer(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(chamfer_l1(a[None], b[None], factor=1.0)[0])


def test_fit_mean_shape_recovers_a_single_shape() -> None:
    sphere = trimesh.creation.icosphere(5, radius=0.3)
    cloud = _surface_points(sphere, 1000, seed=0)
    fitted = fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud] * 3, iterations=150, num_points=1000)
    assert fitted.shape == TEMPLATE_VERTS.shape and fitted.dtype == TEMPLATE_VERTS.dtype
    # dense clouds on both sides, so that the sampling's own Chamfer floor stays well below the threshold
    dense = _surface_points(sphere, 30_000, seed=1)
    before, after = (_chamfer(_mesh_points(v, 30_000), dense) for v in (TEMPLATE_VERTS, fitted))
    assert after < 0.2 * before
    # the surface lies on the sphere (up to the faceting of 162 vertices): exact distances | |p| - r |
    off_before, off_after = ((_mesh_points(v).norm(dim=1) - 0.3).abs() for v in (TEMPLATE_VERTS, fitted))
    assert off_after.mean() < 0.15 * off_before.mean() and (fitted.norm(dim=1) - 0.3).abs().max() < 0.03


def test_a_fit_asked_to_stop_ends_before_its_next_iteration() -> None:
    cloud = _surface_points(trimesh.creation.icosphere(3, radius=0.3), 500, seed=0)
    asked = []

    def after_three() -> bool:  # a signal during the third iteration
        asked.append(len(asked))
        return len(asked) > 3

    assert fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud], iterations=1000, should_stop=after_three) is None
    assert len(asked) == 4  # three iterations run, the fourth not begun
    never = fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud], iterations=5, should_stop=lambda: False)
    assert torch.equal(never, fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud], iterations=5))


def test_fit_mean_shape_beats_every_single_shape() -> None:
    # two boxes, long along X and along Z: no single one of them is the best compromise
    boxes = [trimesh.creation.box(extents=e) for e in ((0.8, 0.3, 0.3), (0.3, 0.3, 0.8))]
    clouds = [_surface_points(b, 1000, seed=i) for i, b in enumerate(boxes)]
    dense = [_surface_points(b, 10_000, seed=10 + i) for i, b in enumerate(boxes)]

    def objective(points: torch.Tensor) -> float:  # the fitted quantity: mean Chamfer-L1 over the shapes
        return sum(_chamfer(points, d) for d in dense) / len(dense)

    options = dict(iterations=150, num_points=1000)
    mean = fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, torch.stack(clouds), **options)  # (M, N, 3) input
    singles = [fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [c], **options) for c in clouds]
    best_single = min(objective(_mesh_points(v)) for v in singles)  # each box fitted alone, same topology
    exact_single = min(objective(_surface_points(b, 10_000, seed=20)) for b in boxes)  # each box itself
    assert objective(_mesh_points(mean)) < 0.9 * min(best_single, exact_single)
    # and no iteration leaves the template as it was
    assert torch.equal(fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, clouds, iterations=0), TEMPLATE_VERTS)


def test_fit_mean_shape_bad_inputs() -> None:
    cloud = torch.rand(50, 3)
    with pytest.raises(ValueError, match="point_clouds is empty"):
        fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [])
    with pytest.raises(ValueError, match=r"point cloud 1 must have shape \(N, 3\)"):
        fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud, torch.rand(50, 2)])
    with pytest.raises(ValueError, match=r"point cloud 0 must have shape \(N, 3\) with N >= 1"):
        fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [torch.zeros(0, 3)])
    with pytest.raises(ValueError, match=r"\(M, N, 3\)"):
        fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, torch.rand(10, 3))
    with pytest.raises(ValueError, match=r"template_verts must have shape \(V, 3\)"):
        fit_mean_shape(TEMPLATE_VERTS[:, :2], TEMPLATE_FACES, [cloud])
    with pytest.raises(ValueError, match="face indices must be in"):
        fit_mean_shape(TEMPLATE_VERTS[:10], TEMPLATE_FACES, [cloud])
    with pytest.raises(ValueError, match="iterations >= 0"):
        fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud], iterations=-1)
    with pytest.raises(ValueError, match="lr > 0"):
        fit_mean_shape(TEMPLATE_VERTS, TEMPLATE_FACES, [cloud], lr=0.0)


def test_the_fits_chamfer_is_chamfer_l1_to_the_last_bit():
    g = torch.Generator().manual_seed(0)
    clouds = torch.rand(6, 300, 3, generator=g)
    clouds[:, 150:] = clouds[:, :150]  # repeated points, as in float16 ground truths
    points = torch.rand(1, 200, 3, generator=g, requires_grad=True)
    pick = torch.tensor([4, 0, 2])
    ref = chamfer_l1(points.expand(3, -1, -1), clouds[pick], factor=1.0).mean()
    (grad_ref,) = torch.autograd.grad(ref, points)
    ours = _sample_chamfer(points, clouds[pick], NearestNeighborIndex(clouds).select(pick))
    (grad,) = torch.autograd.grad(ours, points)
    # the mean shape's fit resamples its surface from the vertices: any rounding difference changes the result
    assert ours.item() == ref.item() and torch.equal(grad, grad_ref)
