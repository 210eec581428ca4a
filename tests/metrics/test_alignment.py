import torch

from unicorn.geometry.rotations import look_at_view_transform
from unicorn.metrics.alignment import align_with_gt_pose, normalize_to_unit_cube


def test_gt_pose_alignment_round_trip():
    g = torch.Generator().manual_seed(0)
    x_gt = torch.rand(2, 30, 3, generator=g) - 0.5
    R_gt, T_gt = look_at_view_transform(2.7, torch.tensor([30.0, 10.0]), torch.tensor([40.0, -120.0]))
    R_pred, T_pred = look_at_view_transform(2.5, torch.tensor([5.0, 25.0]), torch.tensor([100.0, 70.0]))
    # the prediction: the same view-space shape expressed through the predicted pose
    view = x_gt @ R_gt + T_gt.unsqueeze(1)
    x_pred = (view - T_pred.unsqueeze(1)) @ R_pred.transpose(1, 2)
    torch.testing.assert_close(align_with_gt_pose(x_pred, R_pred, T_pred, R_gt, T_gt), x_gt, atol=1e-5, rtol=0)


def test_normalize_to_unit_cube():
    g = torch.Generator().manual_seed(0)
    v = torch.rand(3, 50, 3, generator=g) * torch.tensor([4.0, 1.0, 2.0]) + 7.0
    out, centre, scale = normalize_to_unit_cube(v)
    torch.testing.assert_close(out.abs().amax(dim=(1, 2)), torch.full((3,), 0.5))
    torch.testing.assert_close(out.amin(1) + out.amax(1), torch.zeros(3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close((v - centre.unsqueeze(1)) * scale.view(-1, 1, 1), out)
    point, _, s = normalize_to_unit_cube(torch.ones(1, 4, 3))
    assert (point == 0).all() and s.item() == 1.0
