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


def test_pairs_of_an_odd_number_of_images_follow_the_reference_loop():
    """UNICORN's kp_eval.py: seed 123 + pairs so far, sources ``indices[:middle]``, targets ``indices[-middle:]``."""
    n, num_pairs = 7, 20
    idx0: list[int] = []
    idx1: list[int] = []
    while len(idx0) < num_pairs:
        indices = np.random.RandomState(len(idx0) + 123).permutation(np.arange(0, n))
        middle = n // 2
        idx0, idx1 = idx0 + indices[:middle].tolist(), idx1 + indices[-middle:].tolist()
    src, tgt = keypoint_pairs(n, num_pairs)
    assert src.tolist() == idx0[:num_pairs] and tgt.tolist() == idx1[:num_pairs]


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
    # without explicit pairs two images form two ordered pairs, each used once: the same two directions
    drawn = keypoint_transfer_pck(verts, R, T, visible, kps, 256, num_pairs=10)
    assert drawn == scores


def _naive_pck(verts, R, T, visible, kps, size, alphas):
    """PCK over every ordered pair of distinct images, one keypoint at a time."""
    proj = project_vertices(verts, R, T, size)
    hits, total = [0] * len(alphas), 0
    N, K = kps.shape[:2]
    for a in range(N):
        for b in range(N):
            for k in range(K):
                if a == b or kps[a, k, 2] <= 0 or kps[b, k, 2] <= 0:
                    continue
                total += 1
                seen = [v for v in range(verts.shape[1]) if visible[a, v]]
                nearest = min(seen, key=lambda v: float((proj[a, v] - kps[a, k, :2]).norm()))
                err = float((proj[b, nearest] - kps[b, k, :2]).norm())
                hits = [h + (err <= alpha * size) for h, alpha in zip(hits, alphas)]
    return [h / total for h in hits], total


def test_few_images_use_every_ordered_pair_once():
    g = torch.Generator().manual_seed(3)
    N, V, K = 4, 40, 6
    verts = torch.rand(N, V, 3, generator=g, dtype=torch.float64) - 0.5
    R = torch.eye(3, dtype=torch.float64).expand(N, 3, 3)
    T = torch.tensor([0.0, 0.0, 2.5], dtype=torch.float64).expand(N, 3)
    visible = torch.rand(N, V, generator=g) > 0.3
    kps = torch.rand(N, K, 3, generator=g, dtype=torch.float64) * 256
    kps[..., 2] = (torch.rand(N, K, generator=g) > 0.2).double()
    alphas = (0.05, 0.1, 0.15)
    want, total = _naive_pck(verts, R, T, visible, kps, 256, alphas)
    for num_pairs in (N * (N - 1), 10000):  # the default too
        got = keypoint_transfer_pck(verts, R, T, visible, kps, 256, num_pairs=num_pairs)
        assert [got["pck-5"], got["pck-10"], got["pck-15"]] == pytest.approx(want, abs=1e-12)
        assert got["num-valid"] == total
    # more images than that: the seeded draw of keypoint_pairs, as before
    fewer = keypoint_transfer_pck(verts, R, T, visible, kps, 256, num_pairs=N * (N - 1) - 1)
    assert fewer == keypoint_transfer_pck(verts, R, T, visible, kps, 256, pairs=keypoint_pairs(N, N * (N - 1) - 1))
    with pytest.raises(ValueError, match="2 images"):
        keypoint_transfer_pck(verts[:1], R[:1], T[:1], visible[:1], kps[:1], 256)


def test_invalid_inputs():
    verts, R, T, kps, _ = _scene()
    visible = torch.ones(2, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match="vertex_visibility"):
        keypoint_transfer_pck(verts, R, T, visible.float(), kps, 256)
    with pytest.raises(ValueError, match="keypoints"):
        keypoint_transfer_pck(verts, R, T, visible, kps[..., :2], 256)
    with pytest.raises(ValueError, match="pair indices"):
        keypoint_transfer_pck(verts, R, T, visible, kps, 256, pairs=([0], [2]))
