"""MovingQueries against brute force and against the index's own searches, over clouds that move."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from unicorn.geometry.rotations import euler_angles_to_matrix
from unicorn.metrics.icp import apply_similarity
from unicorn.metrics.moving import MovingQueries
from unicorn.metrics.nn import NearestNeighborIndex, spatial_order
from unicorn.metrics.sampling import sample_points_from_meshes

# pykdtree is a dependency: its absence is an installation error, not a skip
CPU_BACKENDS = ["kdtree", "pykdtree", "torch"]


def brute_force(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N) distances and indices of the nearest point of ``y`` (B, M, 3) to each point of ``x`` (B, N, 3)."""
    return torch.cdist(x.double(), y.double(), compute_mode="donot_use_mm_for_euclid_dist").min(dim=-1)


def _walk(x: torch.Tensor, steps: int, seed: int) -> list[torch.Tensor]:
    """``x`` (B, N, 3) moved by a random similarity per step: mostly small steps as in an ICP, some large jumps."""
    g = torch.Generator().manual_seed(seed)
    B = x.shape[0]
    out = []
    angles, T, s = torch.zeros(B, 3), torch.zeros(B, 3), torch.ones(B, 3)
    for step in range(steps):
        size = 0.3 if step % 7 == 6 else 0.01
        angles = angles + size * torch.randn(B, 3, generator=g)
        T = T + size * torch.randn(B, 3, generator=g)
        s = (s * (1 + size * torch.randn(B, 3, generator=g))).clamp(0.5, 2.0)
        out.append(apply_similarity(x, euler_angles_to_matrix(angles), T, s))
    return out


@pytest.fixture(scope="module")
def surfaces(blob):
    """A source and a target surface sample (B = 2), the target with repeated points."""
    v, f = blob
    src, _ = sample_points_from_meshes(torch.stack([v, 0.9 * v]), f, 700, seed=0)
    tgt, _ = sample_points_from_meshes(torch.stack([1.1 * v, v]), f, 500, seed=1)
    return src, torch.cat([tgt, tgt[:, :100]], dim=1)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("k", [1, 8, 1000])
def test_forward_equals_brute_force_at_every_step(surfaces, backend, k):
    src, tgt = surfaces
    index = NearestNeighborIndex(tgt, backend=backend)
    moving = MovingQueries(index, k=k)
    order = spatial_order(src)
    for x in _walk(src, 15, seed=k):
        d, i = moving.query(x, order)
        d_ref, _ = brute_force(x, tgt)
        torch.testing.assert_close(d.double(), d_ref, atol=1e-6, rtol=0)
        assert torch.equal(i, index.indices(x, order))  # the k-d tree's own answer (no exact ties here)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_reverse_equals_brute_force_at_every_step(surfaces, backend):
    src, tgt = surfaces
    index = NearestNeighborIndex(tgt, backend=backend)
    moving = MovingQueries(index)
    order = spatial_order(src)
    for x in _walk(src, 15, seed=3):
        d, i = moving.reverse_query(x, order)
        d_ref, _ = brute_force(tgt, x)
        torch.testing.assert_close(d.double(), d_ref, atol=1e-6, rtol=0)
        assert torch.equal(i, index.reverse_indices(x, order))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("ordered", [True, False])
def test_both_directions_at_once(surfaces, dtype, ordered):
    """both_indices gives the two directions' answers, for float32 and float64 clouds, with and without an order,
    and for a cloud that is not contiguous in memory."""
    src, tgt = surfaces
    tgt = tgt.to(dtype)
    index = NearestNeighborIndex(tgt)
    moving = MovingQueries(index)
    order = spatial_order(src) if ordered else None
    for x in _walk(src, 8, seed=4):
        x = x.to(dtype)
        x = x.transpose(1, 2).contiguous().transpose(1, 2) if ordered else x
        i_y, i_x = moving.both_indices(x, order)
        assert torch.equal(i_y, brute_force(x, tgt)[1])  # no exact ties here
        torch.testing.assert_close(index.reverse_distances(x, i_x).double(), brute_force(tgt, x)[0], atol=1e-6, rtol=0)
        assert torch.equal(i_x, index.reverse_indices(x, order))


def test_far_jumps_and_degenerate_clouds():
    """A cloud collapsed to a plane, then to one point, then spread again: the grid and the candidates adapt."""
    g = torch.Generator().manual_seed(5)
    y = torch.randn(1, 300, 3, generator=g)
    x = torch.randn(1, 200, 3, generator=g)
    index = NearestNeighborIndex(y)
    moving = MovingQueries(index, k=4)
    flat = x * torch.tensor([1.0, 1.0, 0.0])
    for xi in (x, flat, flat + 5.0, torch.zeros_like(x), x * 3, x):
        assert torch.equal(moving.indices(xi), brute_force(xi, y)[1])
        # a collapsed cloud has exact ties: only the distances are the same
        torch.testing.assert_close(moving.reverse_query(xi)[0].double(), brute_force(y, xi)[0], atol=1e-6, rtol=0)


def test_other_dimensions_use_the_trees():
    g = torch.Generator().manual_seed(6)
    y, x = torch.randn(2, 300, 2, generator=g), torch.randn(2, 200, 2, generator=g)
    moving = MovingQueries(NearestNeighborIndex(y))
    for step in range(4):
        xi = x + 0.02 * step
        assert torch.equal(moving.indices(xi), brute_force(xi, y)[1])
        assert torch.equal(moving.reverse_indices(xi), brute_force(y, xi)[1])


def test_gradients_and_invalid_k(surfaces):
    src, tgt = surfaces
    x = src.clone().requires_grad_(True)
    moving = MovingQueries(NearestNeighborIndex(tgt))
    (moving.query(x)[0].sum() + moving.reverse_query(x)[0].sum()).backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="k must be positive"):
        MovingQueries(NearestNeighborIndex(tgt), k=0)


def _scan_every_cell(q, cloud, grid, cells, r, best_d, best_j):
    """The oracle of ``_scan``: every point of the cells in range, in key order, then the k first by squared
    distance among those nearer than the list's last (stable: the first scanned of equally near points first)."""
    from unicorn.metrics.moving import _MARGIN

    lo, inv, start, members = grid
    r = r * (1.0 + _MARGIN) + _MARGIN
    first = np.clip(np.floor((q - r - lo) * inv).astype(int), 0, cells - 1)
    last = np.clip(np.floor((q + r - lo) * inv).astype(int), 0, cells - 1)
    found = []
    for a in range(first[0], last[0] + 1):
        for b in range(first[1], last[1] + 1):
            for e in range(first[2], last[2] + 1):
                key = (a * cells + b) * cells + e
                for j in members[start[key] : start[key + 1]]:
                    d = float(((q - cloud[j]) ** 2).sum())
                    if d < best_d[-1]:
                        found.append((d, j))
    found = sorted(list(zip(best_d, best_j)) + found, key=lambda f: f[0])[: len(best_d)]
    return np.array([f[0] for f in found]), np.array([f[1] for f in found])


@pytest.mark.parametrize("k", [1, 4, 8])
def test_scan_skips_only_points_that_cannot_enter(k):
    """The scan's row pruning against a scan of every cell, on a lattice (exact ties, points on cell borders)."""
    from unicorn.metrics.moving import _grid, _scan

    rng = np.random.default_rng(k)
    # integer points, extent 12, cells of side 2: duplicates, equal distances, points on the cells' borders
    cloud = np.concatenate([[[0, 0, 0], [12, 12, 12]], rng.integers(0, 13, size=(600, 3))]).astype(np.float64)
    cells = 6
    grid = _grid(cloud, cells)
    queries = np.concatenate([rng.integers(-2, 15, size=(100, 3)), rng.uniform(-1, 13, size=(100, 3))])
    for q in queries:
        for r in (0.0, 1.0, 2.0, 3.5, 8.0):
            start_d = np.full(k, r * r * (1.0 + 1e-12) + 1e-12)
            best_d, best_j = start_d.copy(), np.full(k, -1, np.int64)
            _scan(q, cloud, grid, cells, r, best_d, best_j, np.empty((2, 3), np.int64))
            ref_d, ref_j = _scan_every_cell(q, cloud, grid, cells, r, start_d, np.full(k, -1))
            assert np.array_equal(best_d, ref_d) and np.array_equal(best_j, ref_j), (q, r)


def test_torch_keeps_its_thread_count():
    """The kernels' first use (which starts numba's OpenMP threads) leaves torch's thread count as it was; run in a
    fresh process, where numba has not started them yet."""
    code = (
        "import torch\n"
        "from unicorn.metrics.moving import MovingQueries\n"
        "from unicorn.metrics.nn import NearestNeighborIndex\n"
        "torch.set_num_threads(1)\n"
        "moving = MovingQueries(NearestNeighborIndex(torch.rand(1, 300, 3)))\n"
        "for step in range(3):\n"
        "    moving.both_indices(torch.rand(1, 200, 3))\n"
        "print(torch.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["1"]
