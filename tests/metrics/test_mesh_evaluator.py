import pytest
import torch

from unicorn.geometry.rotations import look_at_view_transform
from unicorn.metrics.alignment import normalize_to_unit_cube
from unicorn.metrics.mesh_evaluator import SHAPENET_METRICS, evaluate_meshes
from unicorn.metrics.sampling import sample_points_from_meshes


@pytest.fixture(scope="module")
def shape(blob):
    v, f = blob
    v, _, _ = normalize_to_unit_cube(v[None])
    gt_points, gt_normals = sample_points_from_meshes(v, f, 3000, seed=10)
    return v, f, gt_points, gt_normals


def test_perfect_prediction_through_poses(shape):
    v, f, gt_points, gt_normals = shape
    R_gt, T_gt = look_at_view_transform(2.7, 30.0, 40.0)
    R_pred, T_pred = look_at_view_transform(2.5, 10.0, 130.0)
    # the prediction: the same view-space shape written in the predicted frame
    view = v @ R_gt + T_gt.unsqueeze(1)
    v_pred = (view - T_pred.unsqueeze(1)) @ R_pred.transpose(1, 2)
    out = evaluate_meshes(
        v_pred,
        f,
        gt_points,
        gt_normals,
        R_pred=R_pred,
        T_pred=T_pred,
        R_gt=R_gt,
        T_gt=T_gt,
        num_points=3000,
        icp_iterations=10,
    )
    assert tuple(out) == SHAPENET_METRICS
    assert all(val.shape == (1,) for val in out.values())
    # sampling noise only: two 3k samplings of a ~0.8-wide surface are ~0.01 apart, x10
    assert out["chamfer-L1"].item() < 0.15
    assert out["chamfer-L1-ICP"].item() < 0.15
    assert out["normal-cos"].item() > 0.95 and out["normal-cos-ICP"].item() > 0.95
    # two samplings of one surface fill almost the same cells (some thin-slice cells hold a point of only one)
    assert out["iou-3d"].item() > 0.9 and out["iou-3d-ICP"].item() > 0.9
    # without the pose alignment the prediction is badly placed
    unaligned = evaluate_meshes(v_pred, f, gt_points, gt_normals, num_points=3000, run_icp=False)
    assert set(unaligned) == {"chamfer-L1", "normal-cos", "iou-3d"}
    assert unaligned["chamfer-L1"].item() > 5 * out["chamfer-L1"].item()
    assert unaligned["iou-3d"].item() < 0.5 * out["iou-3d"].item()


def test_icp_branch_fixes_scale_and_offset(shape):
    v, f, gt_points, gt_normals = shape
    wrong = v * torch.tensor([1.3, 0.8, 1.0]) + 0.1
    out = evaluate_meshes(wrong, f, gt_points, None, num_points=3000, icp_iterations=60)
    assert set(out) == {"chamfer-L1", "chamfer-L1-ICP", "iou-3d", "iou-3d-ICP"}
    assert out["chamfer-L1-ICP"].item() < 0.5 * out["chamfer-L1"].item()
    assert out["iou-3d-ICP"].item() > 0.8 > out["iou-3d"].item()


def test_invalid_inputs(shape):
    v, f, gt_points, gt_normals = shape
    R, T = look_at_view_transform(2.7, 30.0, 40.0)
    with pytest.raises(ValueError, match="all of"):
        evaluate_meshes(v, f, gt_points, R_pred=R, T_pred=T)
    with pytest.raises(ValueError, match="unit cube"):
        evaluate_meshes(v, f, 2 * gt_points, run_icp=False, num_points=10)
    with pytest.raises(ValueError, match="batch"):
        evaluate_meshes(v, f, gt_points.expand(2, -1, -1), run_icp=False, num_points=10)
