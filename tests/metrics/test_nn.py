import importlib.util

import pytest
import torch

from unicorn.checks import ShapeError
from unicorn.geometry.rotations import euler_angles_to_matrix
from unicorn.metrics.nn import (
    BACKENDS,
    NearestNeighborIndex,
    default_backend,
    gather_points,
    nearest_neighbors,
    spatial_order,
)

HAS_PYKDTREE = importlib.util.find_spec("pykdtree") is not None
PYKDTREE = pytest.param("pykdtree", marks=pytest.mark.skipif(not HAS_PYKDTREE, reason="pykdtree not installed"))
CPU_BACKENDS = ["kdtree", PYKDTREE, "torch"]


def brute_force(x, y):
    d = ((x.double().unsqueeze(2) - y.double().unsqueeze(1)) ** 2).sum(-1).sqrt()
    return d.min(dim=2)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("dim", [2, 3])
def test_matches_brute_force(backend, dim):
    g = torch.Generator().manual_seed(0)
    x, y = torch.randn(2, 700, dim, generator=g), torch.randn(2, 500, dim, generator=g) * 2
    d, i = nearest_neighbors(x, y, backend=backend, block_elements=1000)
    d_ref, i_ref = brute_force(x, y)
    assert d.shape == (2, 700) and i.shape == (2, 700) and i.dtype == torch.long
    torch.testing.assert_close(d.double(), d_ref, atol=1e-6, rtol=0)
    # indices may differ only at exact ties
    assert (i == i_ref).float().mean() > 0.999


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_reverse_query_is_the_search_the_other_way(backend):
    g = torch.Generator().manual_seed(1)
    y = torch.randn(2, 400, 3, generator=g)
    y[:, 100:200] = y[:, :100]  # repeated reference points, as in float16 ground truths
    x = torch.randn(2, 300, 3, generator=g) * 1.5
    index = NearestNeighborIndex(y, backend=backend, block_elements=1000)
    d, i = index.reverse_query(x)
    d_ref, _ = brute_force(y, x)
    assert d.shape == (2, 400) and i.shape == (2, 400) and i.dtype == torch.long
    torch.testing.assert_close(d.double(), d_ref, atol=1e-6, rtol=0)
    torch.testing.assert_close(d, torch.linalg.vector_norm(y - x[torch.arange(2)[:, None], i], dim=-1))
    # the same as a fresh search the other way, and the forward query of the same index as nearest_neighbors
    d_fresh, _ = nearest_neighbors(y, x, backend=backend)
    torch.testing.assert_close(d, d_fresh, atol=0, rtol=0)
    d_fwd, i_fwd = index.query(x)
    d_nn, _ = nearest_neighbors(x, y, backend=backend)
    torch.testing.assert_close(d_fwd, d_nn, atol=0, rtol=0)
    torch.testing.assert_close(d_fwd.double(), brute_force(x, y)[0], atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", ["kdtree", PYKDTREE])
def test_trees_take_the_first_copy_of_a_repeated_point(backend):
    y = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0]]])
    x = torch.tensor([[[0.1, 0.0, 0.0], [0.9, 0.1, 0.0], [4.0, 5.0, 5.0]]])
    _, i = NearestNeighborIndex(y, backend=backend).query(x)
    assert i.tolist() == [[0, 1, 4]]
    d, j = NearestNeighborIndex(y, backend=backend).reverse_query(x)
    assert j.tolist() == [[0, 1, 0, 1, 2]]
    torch.testing.assert_close(d, torch.tensor([[0.1, 0.1414214, 0.1, 0.1414214, 1.0]]))


def test_spatial_order_is_a_permutation_that_keeps_neighbours_close():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(2, 2000, 3, generator=g) * torch.tensor([3.0, 1.0, 0.5])
    order = spatial_order(x)
    assert order.shape == (2, 2000) and order.dtype == torch.long
    assert torch.equal(order.sort(dim=1).values, torch.arange(2000).expand(2, -1))

    def mean_step(points):
        return (points[:, 1:] - points[:, :-1]).norm(dim=-1).mean()

    walked = torch.gather(x, 1, order.unsqueeze(-1).expand(-1, -1, 3))
    assert mean_step(walked) < 0.2 * mean_step(x)
    # a similarity transform of the cloud keeps that order a short walk
    moved = 0.7 * x @ euler_angles_to_matrix(torch.tensor([0.3, -0.2, 0.5])) + 4.0
    assert mean_step(torch.gather(moved, 1, order.unsqueeze(-1).expand(-1, -1, 3))) < 0.2 * mean_step(moved)
    # a cloud of one repeated point keeps its order
    assert spatial_order(torch.ones(1, 3, 3)).tolist() == [[0, 1, 2]]


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_visiting_order_changes_no_neighbour(backend):
    g = torch.Generator().manual_seed(3)
    y = torch.randn(2, 400, 3, generator=g)
    y[:, 100:200] = y[:, :100]
    x = torch.randn(2, 300, 3, generator=g) * 1.5
    index = NearestNeighborIndex(y, backend=backend, block_elements=1000)
    random_order = torch.stack([torch.randperm(300, generator=g) for _ in range(2)])
    for order in (spatial_order(x), random_order):
        for method in ("query", "reverse_query"):
            d0, i0 = getattr(index, method)(x)
            d1, i1 = getattr(index, method)(x, order)
            assert torch.equal(i0, i1) and torch.equal(d0, d1)
    if backend != "torch":  # the torch backend ignores the order
        with pytest.raises(ShapeError, match="order"):
            index.query(x, random_order[:, :10])


def test_default_backend():
    assert set(BACKENDS) == {"kdtree", "pykdtree", "torch"}
    assert default_backend() == ("pykdtree" if HAS_PYKDTREE else "kdtree")
    assert NearestNeighborIndex(torch.rand(1, 5, 3)).backend == default_backend()


def test_gradients_flow_through_distances():
    x = torch.rand(1, 50, 3, requires_grad=True)
    y = torch.rand(1, 40, 3, requires_grad=True)
    d, i = nearest_neighbors(x, y)
    d.sum().backward()
    diff = x.detach()[0] - y.detach()[0, i[0]]
    torch.testing.assert_close(x.grad[0], diff / diff.norm(dim=-1, keepdim=True))
    assert y.grad.abs().sum() > 0


@pytest.mark.parametrize("contiguous", [True, False])
def test_gather_points_is_a_gather_with_its_gradient(contiguous):
    """The same values and gradients as torch.gather, repeated indices included (summed in the same order)."""
    g = torch.Generator().manual_seed(0)
    y = torch.randn(3, 3, 40, generator=g).transpose(1, 2)  # (3, 40, 3), not contiguous
    y = (y.contiguous() if contiguous else y).requires_grad_(True)
    idx = torch.randint(0, 40, (3, 500), generator=g)
    w = torch.randn(3, 500, 3, generator=g)
    (gather_points(y, idx) * w).sum().backward()
    ref_y = y.detach().clone().requires_grad_(True)
    ref = torch.gather(ref_y, 1, idx.unsqueeze(-1).expand(-1, -1, 3))
    (ref * w).sum().backward()
    assert torch.equal(gather_points(y, idx), ref) and torch.equal(y.grad, ref_y.grad)


def test_reusable_index_and_dtype_mix():
    y = torch.rand(1, 100, 3, dtype=torch.float64)
    index = NearestNeighborIndex(y, backend="torch")
    d, i = index.query(torch.rand(1, 10, 3))
    assert d.dtype == torch.float32 and i.shape == (1, 10)


@pytest.mark.parametrize(
    ("x", "y", "match"),
    [
        (torch.rand(1, 0, 3), torch.rand(1, 5, 3), "empty"),
        (torch.rand(1, 5, 3), torch.rand(1, 0, 3), "empty"),
        (torch.rand(5, 3), torch.rand(1, 5, 3), "shape"),
        (torch.rand(2, 5, 3), torch.rand(1, 5, 3), "batch"),
        (torch.rand(1, 5, 3), torch.rand(1, 5, 2), "dimension"),
    ],
)
def test_invalid_inputs(x, y, match):
    with pytest.raises(ValueError, match=match):
        nearest_neighbors(x, y)


def test_integer_and_unknown_backend_rejected():
    with pytest.raises(TypeError, match="floating"):
        nearest_neighbors(torch.ones(1, 2, 3, dtype=torch.long), torch.rand(1, 2, 3))
    with pytest.raises(ValueError, match="backend"):
        nearest_neighbors(torch.rand(1, 2, 3), torch.rand(1, 2, 3), backend="faiss")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.gpu
@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_cuda_matches_cpu(backend):
    x, y = torch.rand(1, 3000, 3), torch.rand(1, 2000, 3)
    d_cpu, _ = nearest_neighbors(x, y)
    d_gpu, i_gpu = nearest_neighbors(x.cuda(), y.cuda(), backend=backend)
    assert i_gpu.device.type == "cuda"
    torch.testing.assert_close(d_gpu.cpu(), d_cpu, atol=1e-6, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.gpu
@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_cuda_index_both_directions_match_cpu(backend):
    g = torch.Generator().manual_seed(3)
    y = torch.rand(2, 5000, 3, generator=g)
    y[:, 2500:] = y[:, :2500]  # repeated reference points
    x = torch.rand(2, 7000, 3, generator=g) * 1.2
    cpu, gpu = NearestNeighborIndex(y), NearestNeighborIndex(y.cuda(), backend=backend)
    for name in ("query", "reverse_query"):
        d_cpu, _ = getattr(cpu, name)(x)
        d_gpu, i_gpu = getattr(gpu, name)(x.cuda())
        assert i_gpu.device.type == "cuda"
        torch.testing.assert_close(d_gpu.cpu(), d_cpu, atol=1e-6, rtol=0)
