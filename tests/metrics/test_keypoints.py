import numpy as np
import pytest
import torch

from unicorn.metrics.keypoints import (
    keypoint_pairs,
    keypoint_transfer_pck,
    pck,
    project_vertices,
    transfer_keypoints,
)


def test_transfer_hand_case():
    src_kp = torch.tensor([[[0.0, 0.0], [9.0, 1.0]]])
    src_v = torch.tensor([[[1.0, 0.0], [10.0, 0.0], [0.0, 0.5]]])
    visible = torch.tensor([[True, True, False]])  # the closest vertex to kp 0 (index 2) is hidden
    tgt_v = torch.tensor([[[100.0, 100.0], [200.0, 50.0], [7.0, 7.0]]])
    out, idx = transfer_keypoints(src_kp, src_v, visible, tgt_v)
    assert idx.tolist() == [[0, 1]]
    torch.testing.assert_close(out, torch.tensor([[[100.0, 100.0], [200.0, 50.0]]]))
    out, idx = transfer_keypoints(src_kp, src_v, torch.zeros(1, 3, dtype=torch.bool), tgt_v)
    assert torch.isnan(out).all() and (idx == -1).all()


def test_pck_hand_case():
    pred = torch.tensor([[0.0, 0.0], [3.0, 4.0], [10.0, 0.0], [float("nan"), 0.0]])
    gt = torch.zeros(4, 2)
    valid = torch.tensor([True, True, False, True])
    frac, n = pck(pred, gt, valid, [0.5, 5.0, 100.0])
    assert n == 3
    torch.testing.assert_close(frac, torch.tensor([1 / 3, 2 / 3, 2 / 3]))


def test_pairs_follow_the_seeded_permutation_rule():
    src, tgt = keypoint_pairs(6, 7)
    p0 = np.random.RandomState(123).permutation(6)
    p1 = np.random.RandomState(126).permutation(6)
    assert src.tolist() == list(p0[:3]) + list(p1[:3]) + [np.random.RandomState(129).permutation(6)[0]]
    assert tgt[:6].tolist() == list(p0[3:]) + list(p1[3:])
    s, t = keypoint_pairs(7, 10000)
    assert len(s) == len(t) == 10000 and (s != t).all() and s.max() < 7
    with pytest.raises(ValueError, match="2 images"):
        keypoint_pairs(1)


def _scene():
    """Two images of the same square (4 vertices ~95 px apart at 256 px), same pose."""
    verts = torch.tensor([[-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.2, 0.2, 0.0], [-0.2, 0.2, 0.0]]).expand(2, 4, 3)
    R = torch.eye(3).expand(2, 3, 3)
    T = torch.tensor([0.0, 0.0, 2.0]).expand(2, 3)
    proj = project_vertices(verts, R, T, 256)
    kps = torch.zeros(2, 3, 3)
    kps[:, :, :2] = proj[:, :3]  # keypoint k sits on vertex k
    kps[:, :, 2] = 1.0
    kps[1, 0, 0] += 20.0  # image 1: keypoint 0 off by 20 px (between 0.05 * 256 and 0.1 * 256)
    kps[1, 2, 2] = 0.0  # image 1: keypoint 2 not visible
    return verts, R, T, kps, proj


def test_end_to_end_pck_hand_case():
    verts, R, T, kps, proj = _scene()
    assert (proj[0, 1] - proj[0, 0]).norm() > 80
    visible = torch.ones(2, 4, dtype=torch.bool)
    scores = keypoint_transfer_pck(verts, R, T, visible, kps, 256, pairs=([0], [1]))
    # 0 -> 1: errors 20 (kp 0) and 0 (kp 1); 1 -> 0: 0 and 0; kp 2 invalid
    assert scores == {"pck-5": 0.75, "pck-10": 1.0, "pck-15": 1.0, "num-valid": 4.0}
    # hide vertex 0 in image 1: 1 -> 0 sends kp 0 to a neighbouring vertex (~95 px away)
    visible[1, 0] = False
    scores = keypoint_transfer_pck(verts, R, T, visible, kps, 256, pairs=([0], [1]))
    assert scores == {"pck-5": 0.5, "pck-10": 0.75, "pck-15": 0.75, "num-valid": 4.0}
    # drawn pairs: with two images every pair is (0, 1) or (1, 0), both directions give the same pool
    drawn = keypoint_transfer_pck(verts, R, T, visible, kps, 256, num_pairs=10)
    assert drawn["pck-10"] == 0.75 and drawn["num-valid"] == 40.0


def test_invalid_inputs():
    verts, R, T, kps, _ = _scene()
    visible = torch.ones(2, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match="vertex_visibility"):
        keypoint_transfer_pck(verts, R, T, visible.float(), kps, 256)
    with pytest.raises(ValueError, match="keypoints"):
        keypoint_transfer_pck(verts, R, T, visible, kps[..., :2], 256)
    with pytest.raises(ValueError, match="pair indices"):
        keypoint_transfer_pck(verts, R, T, visible, kps, 256, pairs=([0], [2]))
