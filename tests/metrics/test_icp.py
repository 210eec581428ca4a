import importlib.util

import pytest
import torch

from unicorn.checks import ShapeError
from unicorn.geometry.rotations import euler_angles_to_matrix
from unicorn.metrics.chamfer import point_cloud_scores
from unicorn.metrics.icp import (
    ICPResult,
    apply_similarity,
    gradient_icp,
    matrix_to_rotation_6d,
    rotation_6d_to_matrix,
    transform_normals,
)
from unicorn.metrics.nn import NearestNeighborIndex
from unicorn.metrics.pose import geodesic_error
from unicorn.metrics.sampling import sample_points_from_meshes


def test_rotation_6d_round_trip_and_orthonormal():
    R = euler_angles_to_matrix(torch.randn(20, 3, generator=torch.Generator().manual_seed(0)))
    torch.testing.assert_close(rotation_6d_to_matrix(matrix_to_rotation_6d(R)), R, atol=1e-6, rtol=0)
    M = rotation_6d_to_matrix(torch.randn(20, 6, generator=torch.Generator().manual_seed(1)))
    torch.testing.assert_close(M @ M.transpose(1, 2), torch.eye(3).expand(20, 3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(torch.linalg.det(M), torch.ones(20))


def test_transform_normals_stay_normal_to_the_surface():
    # a plane z = x spanned by tangents t1, t2 with normal n
    t = torch.tensor([[[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]]])
    n = torch.nn.functional.normalize(torch.tensor([[[-1.0, 0.0, 1.0]]]), dim=-1)
    R = euler_angles_to_matrix(torch.tensor([[0.3, -0.2, 0.5]]))
    s = torch.tensor([[2.0, 0.5, 1.5]])
    t2 = apply_similarity(t, R, torch.zeros(1, 3), s)  # linear part only, T = 0
    n2 = transform_normals(n, R, s)
    assert (t2 @ n2.transpose(1, 2)).abs().max() < 1e-6
    assert n2.norm(dim=-1).sub(1).abs().max() < 1e-6


def test_icp_recovers_rotation_translation_anisotropic_scale(blob):
    v, f = blob
    src, src_n = sample_points_from_meshes(v[None], f, 3000, seed=0)
    tgt0, tgt0_n = sample_points_from_meshes(v[None], f, 3000, seed=1)  # different samples of the same surface
    R = euler_angles_to_matrix(torch.tensor([[0.2, -0.3, 0.25]]))  # 24 degrees
    s = torch.tensor([[1.2, 0.85, 1.1]])
    T = torch.tensor([[0.05, -0.08, 0.1]])
    tgt = apply_similarity(tgt0, R, T, s)
    tgt_n = transform_normals(tgt0_n, R, s)
    before = point_cloud_scores(src, tgt, src_n, tgt_n)
    with torch.no_grad():  # runs with gradients internally anyway
        res = gradient_icp(src, tgt, src_n, n_iter=100)
    assert geodesic_error(res.R, R).item() < 2.0
    torch.testing.assert_close(res.T, T, atol=0.003, rtol=0)  # a few per cent of each component
    torch.testing.assert_close(res.scale, s, atol=0.006, rtol=0)
    after = point_cloud_scores(res.points, tgt, res.normals, tgt_n)
    assert after.chamfer_l1.item() < 0.3 * before.chamfer_l1.item()
    assert after.normal_cos.item() > 0.97 > before.normal_cos.item()


def test_icp_per_object_batch_and_options(blob):
    v, f = blob
    src, _ = sample_points_from_meshes(torch.stack([v, v]), f, 500, seed=0)
    tgt = src + torch.tensor([[[0.05, 0.0, 0.0]], [[0.0, -0.05, 0.0]]])
    res = gradient_icp(src, tgt, n_iter=40, estimate_scale=False)
    assert (res.scale == 1).all() and res.loss.shape == (2,)
    torch.testing.assert_close(res.T, torch.tensor([[0.05, 0.0, 0.0], [0.0, -0.05, 0.0]]), atol=0.002, rtol=0)
    for anisotropic in (True, False):  # a cloud grown by 1.1 about the origin: scale 1.1, no translation
        iso = gradient_icp(src, 1.1 * src, n_iter=30, anisotropic_scale=anisotropic, window=7 if anisotropic else 10)
        assert iso.scale.shape == (2, 3)
        torch.testing.assert_close(iso.scale, torch.full((2, 3), 1.1), atol=0.01, rtol=0)
        torch.testing.assert_close(iso.T, torch.zeros(2, 3), atol=0.003, rtol=0)
    assert torch.allclose(iso.scale, iso.scale[:, :1].expand(2, 3))  # isotropic: one factor


def _reference_icp(src, tgt, src_normals, n_iter, lr=0.01, window=10):
    """The ICP searched by brute force, both directions afresh at every iteration (anisotropic scale): the oracle
    of :func:`gradient_icp`'s shared and deduplicated searches."""

    def nearest(x, y):  # (B, N) distances from x to y, differentiable, with brute-force indices
        idx = torch.cdist(x.detach().double(), y.detach().double()).argmin(-1)
        return torch.linalg.vector_norm(x - y[torch.arange(x.shape[0])[:, None], idx], dim=-1)

    B = src.shape[0]
    d6 = src.new_tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]).repeat(B, 1).requires_grad_(True)
    T = src.new_zeros(B, 3).requires_grad_(True)
    s = src.new_ones(B, 3).requires_grad_(True)
    optimizer = torch.optim.Adam([d6, T, s], lr=lr)
    best_loss, best, losses = src.new_full((B,), float("inf")), [p.detach().clone() for p in (d6, T, s)], []
    for it in range(n_iter):
        optimizer.zero_grad()
        moved = apply_similarity(src, rotation_6d_to_matrix(d6), T, s)
        loss = nearest(moved, tgt).square().mean(1) + nearest(tgt, moved).square().mean(1)
        loss.mean().backward()
        optimizer.step()
        losses.append(loss.detach())
        if (it + 1) % window == 0 or it + 1 == n_iter:
            mean, losses = torch.stack(losses).mean(0), []
            better = mean < best_loss
            best_loss = torch.where(better, mean, best_loss)
            for kept, current in zip(best, (d6, T, s)):
                kept.copy_(torch.where(better.view(B, 1), current.detach(), kept))
    with torch.no_grad():
        R = rotation_6d_to_matrix(best[0])
        points = apply_similarity(src, R, best[1], best[2])
        return ICPResult(points, transform_normals(src_normals, R, best[2]), R, best[1], best[2], best_loss)


PYKDTREE = pytest.param(
    "pykdtree", marks=pytest.mark.skipif(importlib.util.find_spec("pykdtree") is None, reason="pykdtree not installed")
)


@pytest.mark.parametrize("backend", ["kdtree", PYKDTREE, "torch"])
@pytest.mark.parametrize("shared_index", [False, True])
def test_icp_matches_the_brute_force_oracle(blob, backend, shared_index):
    v, f = blob
    src, src_n = sample_points_from_meshes(torch.stack([v, 0.9 * v]), f, 400, seed=0)
    tgt, _ = sample_points_from_meshes(torch.stack([v, v]), f, 600, seed=1)
    tgt = apply_similarity(
        tgt, euler_angles_to_matrix(torch.tensor([[0.2, 0.1, -0.1]] * 2)), torch.zeros(2, 3), 1.1 * torch.ones(2, 3)
    )
    tgt = torch.cat([tgt, tgt[:, :200]], dim=1)  # repeated target points, as in float16 ground truths
    index = NearestNeighborIndex(tgt, backend=backend) if shared_index else None
    res = gradient_icp(src, tgt, src_n, n_iter=25, backend=backend, tgt_index=index)
    ref = _reference_icp(src, tgt, src_n, n_iter=25)
    for name in ICPResult._fields:
        torch.testing.assert_close(getattr(res, name), getattr(ref, name), atol=1e-6, rtol=1e-5, msg=name)
    if shared_index:  # the index is reusable: a second ICP on it gives the same result
        again = gradient_icp(src, tgt, src_n, n_iter=25, tgt_index=index)
        torch.testing.assert_close(again.points, res.points, atol=0, rtol=0)


def test_icp_invalid_inputs():
    with pytest.raises(ShapeError, match=r"d6 must have shape \(\.\.\., 6\)"):
        rotation_6d_to_matrix(torch.rand(2, 5))
    with pytest.raises(ShapeError, match="R must have shape"):
        matrix_to_rotation_6d(torch.rand(2, 3, 2))
    x = torch.rand(1, 10, 3)
    with pytest.raises(ValueError, match="n_iter"):
        gradient_icp(x, x, n_iter=0)
    with pytest.raises(ValueError, match="lr"):
        gradient_icp(x, x, lr=0.0)
    with pytest.raises(ValueError, match="src_normals"):
        gradient_icp(x, x, torch.rand(1, 9, 3))
    with pytest.raises(ValueError, match="tgt_index"):
        gradient_icp(x, x, tgt_index=NearestNeighborIndex(torch.rand(1, 11, 3)))
