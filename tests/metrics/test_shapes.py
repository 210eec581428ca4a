"""Shape retrieval and spread against independent computations (pairwise and double loops)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from unicorn.metrics import (
    chamfer_matrix,
    mesh_spread,
    normalize_shape,
    retrieval_scores,
    shape_retrieval,
    shape_spread,
)
from unicorn.metrics.icp import rotation_6d_to_matrix


def _rotations(n: int, g: torch.Generator) -> torch.Tensor:
    return rotation_6d_to_matrix(torch.randn(n, 6, generator=g, dtype=torch.float64))


def _objects(n: int, points: int, g: torch.Generator) -> torch.Tensor:
    """n random anisotropic blobs (C, M, 3): distinct shapes of different proportions."""
    cloud = torch.randn(n, points, 3, generator=g, dtype=torch.float64)
    return cloud * (0.2 + torch.rand(n, 1, 3, generator=g, dtype=torch.float64))


def _brute_chamfer(a: torch.Tensor, b: torch.Tensor) -> float:
    d = torch.cdist(a, b)
    return 0.5 * float(d.min(dim=1).values.mean() + d.min(dim=0).values.mean())


def test_chamfer_matrix_matches_a_pairwise_loop() -> None:
    g = torch.Generator().manual_seed(0)
    x, y = torch.randn(3, 40, 3, generator=g), torch.randn(4, 30, 3, generator=g)
    for backend in ("kdtree", "torch"):
        got = chamfer_matrix(x, y, factor=1.0, backend=backend)
        want = [[_brute_chamfer(x[p], y[q]) for q in range(4)] for p in range(3)]
        np.testing.assert_allclose(got.numpy(), np.array(want), rtol=1e-5)


def test_shape_retrieval_matches_a_double_loop_in_view_coordinates() -> None:
    g = torch.Generator().manual_seed(1)
    Q, C = 7, 5
    candidates = _objects(C, 50, g)
    targets = torch.randint(0, C, (Q,), generator=g)
    R, T = _rotations(Q, g), torch.randn(Q, 3, generator=g, dtype=torch.float64)
    # noisy, rescaled reconstructions of each image's object, in view coordinates
    queries = (candidates[targets] + 0.3 * torch.randn(Q, 50, 3, generator=g, dtype=torch.float64)) @ R
    queries = queries * torch.rand(Q, 1, 1, generator=g, dtype=torch.float64) + T[:, None]
    got = shape_retrieval(queries[:, :40], R, candidates, targets)

    def normalised(x: np.ndarray) -> np.ndarray:
        x = x - x.mean(axis=0)
        return x / np.sqrt((x**2).sum(axis=1).mean())

    top1, top3, rr = [], [], []
    for q in range(Q):
        d = []
        for c in range(C):
            seen = candidates[c].numpy() @ R[q].numpy() + T[q].numpy()  # object c seen in image q's view
            d.append(_brute_chamfer(torch.tensor(normalised(queries[q, :40].numpy())), torch.tensor(normalised(seen))))
        rank = 1 + sum(x < d[targets[q]] for x in d)
        top1.append(rank <= 1)
        top3.append(rank <= 3)
        rr.append(1 / rank)
        np.testing.assert_allclose(got["distances"][q].numpy(), d, rtol=1e-9)
    assert got["top1"].tolist() == top1 and got["top3"].tolist() == top3
    np.testing.assert_allclose(got["rr"].numpy(), rr, rtol=1e-12)


def test_shape_retrieval_of_exact_and_rescaled_ground_truth() -> None:
    g = torch.Generator().manual_seed(2)
    Q, C = 12, 6
    candidates = _objects(C, 200, g)
    targets = torch.arange(Q) % C
    R, T = _rotations(Q, g), torch.randn(Q, 3, generator=g, dtype=torch.float64)
    exact = candidates[targets] @ R + T[:, None]
    got = shape_retrieval(exact, R, candidates, targets)
    assert got["top1"].tolist() == [1.0] * Q and got["rr"].tolist() == [1.0] * Q
    # normalisation: any size and distance of each reconstruction gives the same distances
    scale = 0.1 + 5 * torch.rand(Q, 1, 1, generator=g, dtype=torch.float64)
    noisy = exact + 0.2 * torch.randn(Q, 200, 3, generator=g, dtype=torch.float64)
    a = shape_retrieval(noisy, R, candidates, targets)
    b = shape_retrieval(noisy * scale + torch.randn(Q, 1, 3, generator=g, dtype=torch.float64), R, candidates, targets)
    torch.testing.assert_close(a["distances"], b["distances"])
    assert a["top1"].tolist() == b["top1"].tolist()
    torch.testing.assert_close(normalize_shape(noisy * scale), normalize_shape(noisy))


def test_one_shape_for_every_image_scores_chance() -> None:
    g = torch.Generator().manual_seed(3)
    C = 8
    candidates = _objects(C, 100, g)
    constant = _objects(1, 100, g)[0]
    # one query per object, all in one view, the same shape at any size: exactly chance
    R = _rotations(1, g).expand(C, 3, 3)
    queries = constant * (0.5 + torch.rand(C, 1, 1, generator=g, dtype=torch.float64)) @ R
    got = shape_retrieval(queries, R, candidates, torch.arange(C))
    assert float(got["top1"].mean()) == pytest.approx(1 / C)
    assert float(got["top3"].mean()) == pytest.approx(3 / C)
    assert float(got["rr"].mean()) == pytest.approx(sum(1 / r for r in range(1, C + 1)) / C)
    # random views and objects: chance in expectation (1000 queries: 1/C +- 0.01 standard error)
    hits = []
    for _ in range(25):
        candidates = _objects(C, 60, g)
        targets = torch.randint(0, C, (40,), generator=g)
        R = _rotations(40, g)
        hits.append(shape_retrieval(constant[:60].expand(40, 60, 3) @ R, R, candidates, targets)["top1"])
    assert float(torch.cat(hits).mean()) == pytest.approx(1 / C, abs=0.03)


def test_retrieval_scores_break_ties_in_expectation() -> None:
    d = torch.tensor([[1.0, 1.0, 1.0, 1.0], [0.5, 1.0, 1.0, 2.0]])
    got = retrieval_scores(d, torch.tensor([2, 1]), ks=(1, 2, 3))
    # all tied: rank uniform over 1..4; second row: one closer, one tie: rank 2 or 3
    assert got["top1"].tolist() == [0.25, 0.0]
    assert got["top2"].tolist() == [0.5, 0.5]
    assert got["top3"].tolist() == [0.75, 1.0]
    np.testing.assert_allclose(got["rr"].numpy(), [(1 + 1 / 2 + 1 / 3 + 1 / 4) / 4, (1 / 2 + 1 / 3) / 2])
    with pytest.raises(ValueError, match="targets"):
        retrieval_scores(d, torch.tensor([0, 4]))


def test_shape_spread_against_a_pair_loop() -> None:
    g = torch.Generator().manual_seed(4)
    clouds = _objects(5, 30, g)
    objects = torch.tensor([0, 1, 1, 2, 3])
    normed = normalize_shape(clouds)
    want = [_brute_chamfer(normed[i], normed[j]) for i in range(5) for j in range(5) if objects[i] != objects[j]]
    assert shape_spread(clouds, objects) == pytest.approx(float(np.mean(want)), rel=1e-9)
    # one shape at several sizes: no spread; stretched along the axes: no spread beyond the proportions
    assert shape_spread(clouds[:1] * torch.tensor([1.0, 2.0, 0.3])[:, None, None]) == pytest.approx(0.0, abs=1e-12)
    stretched = clouds[:1] * (0.5 + torch.rand(4, 1, 3, generator=g, dtype=torch.float64))
    assert shape_spread(stretched) > 0.01
    assert shape_spread(stretched, per_axis=True) == pytest.approx(0.0, abs=1e-12)
    axes = normalize_shape(stretched, per_axis=True)
    torch.testing.assert_close(axes.square().mean(dim=1), torch.full((4, 3), 1 / 3, dtype=torch.float64))
    assert math.isnan(shape_spread(clouds[:2], torch.tensor([7, 7])))


def test_mesh_spread_against_a_vertex_loop() -> None:
    g = torch.Generator().manual_seed(5)
    verts = torch.randn(4, 12, 3, generator=g, dtype=torch.float64)
    for per_axis in (False, True):
        meshes = [m.numpy() - m.numpy().mean(axis=0) for m in verts]
        if per_axis:
            meshes = [m / np.sqrt(3 * (m**2).mean(axis=0)) for m in meshes]
        else:
            meshes = [m / np.sqrt((m**2).sum(axis=1).mean()) for m in meshes]
        mean = [np.mean([n[v] for n in meshes], axis=0) for v in range(12)]
        want = np.mean([np.linalg.norm(m[v] - mean[v]) for m in meshes for v in range(12)])
        assert mesh_spread(verts, per_axis=per_axis) == pytest.approx(want, rel=1e-9)
    # one shape at several sizes and stretches, moved about: no spread beyond its proportions; with them, some
    shift = torch.randn(3, 1, 3, generator=g, dtype=torch.float64)
    stretched = verts[:1] * (0.5 + torch.rand(3, 1, 3, generator=g, dtype=torch.float64)) + shift
    assert mesh_spread(stretched) == pytest.approx(0.0, abs=1e-12)
    assert mesh_spread(stretched, per_axis=False) > 0.01
    assert mesh_spread(verts[:1]) == 0.0
