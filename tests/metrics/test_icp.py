import pytest
import torch

from unicorn.geometry.rotations import euler_angles_to_matrix
from unicorn.metrics.chamfer import point_cloud_scores
from unicorn.metrics.icp import (
    apply_similarity,
    gradient_icp,
    matrix_to_rotation_6d,
    rotation_6d_to_matrix,
    transform_normals,
)
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
    torch.testing.assert_close(res.T, T, atol=0.01, rtol=0)
    torch.testing.assert_close(res.scale, s, atol=0.01, rtol=0)
    after = point_cloud_scores(res.points, tgt, res.normals, tgt_n)
    assert after.chamfer_l1.item() < 0.3 * before.chamfer_l1.item()
    assert after.normal_cos.item() > 0.97 > before.normal_cos.item()


def test_icp_per_object_batch_and_options(blob):
    v, f = blob
    src, _ = sample_points_from_meshes(torch.stack([v, v]), f, 500, seed=0)
    tgt = src + torch.tensor([[[0.05, 0.0, 0.0]], [[0.0, -0.05, 0.0]]])
    res = gradient_icp(src, tgt, n_iter=40, estimate_scale=False)
    assert (res.scale == 1).all() and res.loss.shape == (2,)
    torch.testing.assert_close(res.T, torch.tensor([[0.05, 0.0, 0.0], [0.0, -0.05, 0.0]]), atol=0.01, rtol=0)
    iso = gradient_icp(src, 1.1 * src, n_iter=30, anisotropic_scale=True, window=7)
    assert iso.scale.shape == (2, 3)
    iso = gradient_icp(src, 1.1 * src, n_iter=30, anisotropic_scale=False)
    assert torch.allclose(iso.scale, iso.scale[:, :1].expand(2, 3))


def test_icp_invalid_inputs():
    x = torch.rand(1, 10, 3)
    with pytest.raises(ValueError, match="n_iter"):
        gradient_icp(x, x, n_iter=0)
    with pytest.raises(ValueError, match="lr"):
        gradient_icp(x, x, lr=0.0)
    with pytest.raises(ValueError, match="src_normals"):
        gradient_icp(x, x, torch.rand(1, 9, 3))
