import numpy as np
import pytest
import torch

from unicorn.metrics.chamfer import chamfer_l1, chamfer_l2, normal_consistency, point_cloud_scores


def o3d_mean_distance(a: np.ndarray, b: np.ndarray) -> float:
    import open3d as o3d  # imported where used: the gpu tests run where open3d is not installed

    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a.astype(np.float64)))
    pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b.astype(np.float64)))
    return float(np.mean(np.asarray(pa.compute_point_cloud_distance(pb))))


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
def test_chamfer_l1_matches_open3d(backend):
    rng = np.random.default_rng(0)
    pred = rng.uniform(-0.5, 0.5, (2, 3000, 3))
    gt = rng.normal(0, 0.2, (2, 2000, 3))
    pred_n, gt_n = rng.normal(size=pred.shape), rng.normal(size=gt.shape)  # not unit: normalised by the metric
    scores = point_cloud_scores(*map(torch.tensor, (pred, gt, pred_n, gt_n)), backend=backend)
    for b in range(2):
        acc, comp = o3d_mean_distance(pred[b], gt[b]), o3d_mean_distance(gt[b], pred[b])
        assert scores.accuracy[b].item() == pytest.approx(acc, rel=1e-9)
        assert scores.completeness[b].item() == pytest.approx(comp, rel=1e-9)
        assert scores.chamfer_l1[b].item() == pytest.approx(10 * 0.5 * (acc + comp), rel=1e-9)
        # normal consistency: mean |cos| to the nearest point's normal, each way (nearest by a full distance matrix)
        d2 = ((pred[b][:, None] - gt[b][None]) ** 2).sum(-1)
        unit_p = pred_n[b] / np.linalg.norm(pred_n[b], axis=-1, keepdims=True)
        unit_g = gt_n[b] / np.linalg.norm(gt_n[b], axis=-1, keepdims=True)
        cos_pred = np.abs((unit_p * unit_g[d2.argmin(1)]).sum(-1)).mean()
        cos_gt = np.abs((unit_g * unit_p[d2.argmin(0)]).sum(-1)).mean()
        assert scores.normal_cos[b].item() == pytest.approx(0.5 * (cos_pred + cos_gt), rel=1e-9)
    torch.testing.assert_close(chamfer_l1(torch.tensor(pred), torch.tensor(gt)), scores.chamfer_l1)


def test_chamfer_hand_case_and_factor():
    x = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    y = torch.tensor([[[0.0, 0.3, 0.0]]])
    # accuracy = (0.3 + sqrt(1.09)) / 2, completeness = 0.3
    expected = 0.5 * ((0.3 + 1.09**0.5) / 2 + 0.3)
    assert chamfer_l1(x, y, factor=1.0).item() == pytest.approx(expected, rel=1e-6)
    assert chamfer_l1(x, y).item() == pytest.approx(10 * expected, rel=1e-6)
    assert chamfer_l2(x, y).item() == pytest.approx((0.09 + 1.09) / 2 + 0.09, rel=1e-6)
    assert chamfer_l1(x, x).item() == 0.0


def test_normal_consistency():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1, 200, 3, generator=g)
    n = torch.nn.functional.normalize(torch.randn(1, 200, 3, generator=g), dim=-1)
    # identical clouds: normals flipped in sign still count as consistent (|cos|)
    assert normal_consistency(pts, -n, pts, n).item() == pytest.approx(1.0, abs=1e-6)
    perp = torch.nn.functional.normalize(torch.cross(n, torch.randn(1, 200, 3, generator=g), dim=-1), dim=-1)
    assert normal_consistency(pts, perp, pts, n).item() == pytest.approx(0.0, abs=1e-6)
    # unnormalised normals are normalised
    assert normal_consistency(pts, 3 * n, pts, n).item() == pytest.approx(1.0, abs=1e-6)


def test_invalid_inputs():
    with pytest.raises(ValueError, match="both"):
        point_cloud_scores(torch.rand(1, 5, 3), torch.rand(1, 5, 3), pred_normals=torch.rand(1, 5, 3))
    with pytest.raises(ValueError, match="shape"):
        point_cloud_scores(torch.rand(1, 5, 3), torch.rand(1, 5, 3), torch.rand(1, 4, 3), torch.rand(1, 5, 3))
    with pytest.raises(ValueError, match="empty"):
        chamfer_l1(torch.rand(1, 0, 3), torch.rand(1, 5, 3))
    with pytest.raises(ValueError, match="batch"):
        chamfer_l1(torch.rand(2, 5, 3), torch.rand(3, 5, 3))
