import pytest
import torch

from unicorn.geometry.rotations import look_at_view_transform
from unicorn.metrics.alignment import normalize_to_unit_cube
from unicorn.metrics.mesh_evaluator import SHAPENET_METRICS, evaluate_meshes
from unicorn.metrics.nn import NearestNeighborIndex
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


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
def test_a_shared_ground_truth_index_gives_the_same_scores(shape, backend):
    v, f, gt_points, gt_normals = shape
    gt = torch.cat([gt_points, gt_points[:, :500]], dim=1)  # repeated points, as in float16 ground truths
    gt_n = torch.cat([gt_normals, gt_normals[:, :500]], dim=1)
    preds = [v * torch.tensor([1.2, 0.9, 1.0]) + 0.05, v * 0.8]
    index = NearestNeighborIndex(gt, backend=backend)
    for pred in preds:
        alone = evaluate_meshes(pred, f, gt, gt_n, num_points=1000, icp_iterations=15, backend=backend)
        shared = evaluate_meshes(pred, f, gt, gt_n, num_points=1000, icp_iterations=15, gt_index=index)
        assert set(shared) == set(SHAPENET_METRICS)
        for k in SHAPENET_METRICS:
            torch.testing.assert_close(shared[k], alone[k], atol=0, rtol=0)
        icp_only = evaluate_meshes(
            pred, f, gt, gt_n, num_points=1000, icp_iterations=15, run_direct=False, backend=backend
        )
        assert set(icp_only) == {"chamfer-L1-ICP", "normal-cos-ICP", "iou-3d-ICP"}
        torch.testing.assert_close(icp_only["chamfer-L1-ICP"], alone["chamfer-L1-ICP"], atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="gt_index"):
        evaluate_meshes(v, f, gt_points, gt_normals, gt_index=index)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.gpu
def test_cuda_scores_match_cpu(shape):
    v, f, gt_points, gt_normals = shape
    pred = v * torch.tensor([1.2, 0.9, 1.0]) + 0.05
    kwargs = dict(num_points=5000, icp_iterations=20)
    cpu = evaluate_meshes(pred, f, gt_points, gt_normals, **kwargs)
    index = NearestNeighborIndex(gt_points.cuda())
    gpu = evaluate_meshes(pred.cuda(), f.cuda(), gt_points.cuda(), gt_normals.cuda(), **kwargs, gt_index=index)
    assert set(gpu) == set(cpu)
    for k in cpu:
        assert gpu[k].device.type == "cuda"
        # the same neighbours; float32 sums in another order, through 20 Adam steps
        torch.testing.assert_close(gpu[k].cpu(), cpu[k], atol=0, rtol=1e-4, msg=k)


def test_invalid_inputs(shape):
    v, f, gt_points, gt_normals = shape
    R, T = look_at_view_transform(2.7, 30.0, 40.0)
    with pytest.raises(ValueError, match="all of"):
        evaluate_meshes(v, f, gt_points, R_pred=R, T_pred=T)
    with pytest.raises(ValueError, match="unit cube"):
        evaluate_meshes(v, f, 2 * gt_points, run_icp=False, num_points=10)
    with pytest.raises(ValueError, match="batch"):
        evaluate_meshes(v, f, gt_points.expand(2, -1, -1), run_icp=False, num_points=10)
