import pytest
import torch

from unicorn.metrics.nn import NearestNeighborIndex, nearest_neighbors


def brute_force(x, y):
    d = ((x.double().unsqueeze(2) - y.double().unsqueeze(1)) ** 2).sum(-1).sqrt()
    return d.min(dim=2)


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
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


def test_gradients_flow_through_distances():
    x = torch.rand(1, 50, 3, requires_grad=True)
    y = torch.rand(1, 40, 3, requires_grad=True)
    d, i = nearest_neighbors(x, y)
    d.sum().backward()
    diff = x.detach()[0] - y.detach()[0, i[0]]
    torch.testing.assert_close(x.grad[0], diff / diff.norm(dim=-1, keepdim=True))
    assert y.grad.abs().sum() > 0


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
def test_cuda_matches_cpu():
    x, y = torch.rand(1, 3000, 3), torch.rand(1, 2000, 3)
    d_cpu, _ = nearest_neighbors(x, y)
    d_gpu, i_gpu = nearest_neighbors(x.cuda(), y.cuda())
    assert i_gpu.device.type == "cuda"
    torch.testing.assert_close(d_gpu.cpu(), d_cpu, atol=1e-6, rtol=0)
