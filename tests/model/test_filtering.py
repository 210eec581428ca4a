"""Separable filters, SSIM and Sobel against direct convolutions and kornia (the independent references)."""

from __future__ import annotations

import kornia
import pytest
import torch
import torch.nn.functional as F

from unicorn.model.filtering import separable_filter
from unicorn.model.generator import Blur
from unicorn.objectives.perceptual import StructuralLoss, sobel_gradient, ssim_map


def _conv_reference(x: torch.Tensor, ty: list[float], tx: list[float], mode: str) -> torch.Tensor:
    """Pad, then one dense 2-D correlation per channel with the outer-product kernel."""
    p = len(ty) // 2
    kernel = torch.tensor(ty, dtype=x.dtype)[:, None] * torch.tensor(tx, dtype=x.dtype)[None, :]
    C = x.shape[1]
    xp = F.pad(x, (p, p, p, p), mode=mode)
    return F.conv2d(xp, kernel.expand(C, 1, *kernel.shape), groups=C)


TAPS = [([1.0], [1.0]), ([0.25, 0.5, 0.25], [-0.5, 0.0, 0.5]), ([0.1, 0.2, 0.4, 0.2, 0.1],) * 2]


@pytest.mark.parametrize("mode", ["reflect", "replicate"])
@pytest.mark.parametrize("size", [(3, 3), (5, 7), (16, 9)])
@pytest.mark.parametrize("taps", TAPS)
def test_separable_filter_matches_padded_convolution(mode, size, taps):
    ty, tx = taps
    g = torch.Generator().manual_seed(0)
    x = torch.rand(3, 2, *size, generator=g, dtype=torch.float64)
    torch.testing.assert_close(separable_filter(x, ty, tx, mode), _conv_reference(x, ty, tx, mode))


def test_separable_filter_rejects_even_taps():
    with pytest.raises(ValueError, match="odd number of taps"):
        separable_filter(torch.rand(1, 1, 4, 4), [0.5, 0.5], [1.0], "reflect")


@pytest.mark.parametrize("window", [1, 3, 5])
def test_ssim_map_matches_kornia(window):
    g = torch.Generator().manual_seed(1)
    x, y = torch.rand(2, 4, 3, 12, 10, generator=g, dtype=torch.float64)
    torch.testing.assert_close(ssim_map(x, y, window), kornia.metrics.ssim(x, y, window, max_val=1.0))


def test_sobel_gradient_matches_kornia():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(2, 3, 9, 11, generator=g, dtype=torch.float64)
    torch.testing.assert_close(sobel_gradient(x), kornia.filters.spatial_gradient(x))


def test_blur_matches_depthwise_convolution():
    g = torch.Generator().manual_seed(3)
    k = [0.25, 0.5, 0.25]
    for side in (2, 8):  # the generators blur from 2 x 2 up
        x = torch.rand(2, 3, side, side, generator=g, dtype=torch.float64)
        torch.testing.assert_close(Blur()(x), _conv_reference(x, k, k, "reflect"))


def _kornia_structural(rec: torch.Tensor, target: torch.Tensor, n_scales: int = 3, window: int = 5) -> torch.Tensor:
    """The loss written with kornia's own SSIM and Sobel filters."""
    total = rec.new_zeros(rec.shape[0])
    for s in range(n_scales):
        if s > 0:
            rec, target = F.avg_pool2d(rec, 2), F.avg_pool2d(target, 2)
        w = max(min(window, 2 * (min(rec.shape[-2:]) // 2) - 1), 1)
        ssim = kornia.metrics.ssim(rec, target, w, max_val=1.0)
        grad = kornia.filters.spatial_gradient(rec) - kornia.filters.spatial_gradient(target)
        total = total + ((1 - ssim) / 2).flatten(1).mean(1) + grad.abs().flatten(1).mean(1)
    return total / n_scales


def test_structural_loss_and_gradient_match_kornia():
    g = torch.Generator().manual_seed(4)
    rec = torch.rand(3, 3, 16, 16, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(3, 3, 16, 16, generator=g, dtype=torch.float64)
    ours, ref = StructuralLoss()(rec, target), _kornia_structural(rec, target)
    torch.testing.assert_close(ours, ref)
    (g_ours,) = torch.autograd.grad(ours.sum(), rec)
    (g_ref,) = torch.autograd.grad(ref.sum(), rec)
    torch.testing.assert_close(g_ours, g_ref)


def test_cached_filter_matrix_first_built_under_inference_mode_serves_autograd():
    # the matrices are built once and shared; one first asked for under inference_mode must still be a normal
    # tensor that a later training step's autograd can save, and give the same values
    x = torch.rand(2, 3, 13, 11)
    with torch.inference_mode():
        first = separable_filter(x.clone(), [0.2, 0.6, 0.2], [0.1, 0.8, 0.1], "reflect")
    y = x.clone().requires_grad_(True)
    again = separable_filter(y, [0.2, 0.6, 0.2], [0.1, 0.8, 0.1], "reflect")
    again.square().sum().backward()
    torch.testing.assert_close(again.detach(), first)
    torch.testing.assert_close(again.detach(), _conv_reference(x, [0.2, 0.6, 0.2], [0.1, 0.8, 0.1], "reflect"))
    assert y.grad is not None and torch.isfinite(y.grad).all()


def test_compiled_filter_asks_the_cache_through_one_operator_per_matrix():
    # a traced graph holds one unicorn::filter_matrix call per matrix, not the ops that build it, and its values
    # and gradients are those of the padded convolution (aot_eager: AOTAutograd differentiates the graph)
    graphs: list[torch.fx.GraphModule] = []

    def record(gm: torch.fx.GraphModule, example_inputs: list) -> torch.fx.GraphModule:
        graphs.append(gm)
        return gm

    ty, tx = [0.1, 0.2, 0.4, 0.2, 0.1], [-0.3, 0.1, 0.2, 0.6, 0.4]
    x = torch.rand(2, 3, 9, 7, dtype=torch.float64, requires_grad=True)
    traced = torch.compile(lambda x: separable_filter(x, ty, tx, "reflect"), backend=record, fullgraph=True)
    traced(x.detach())
    (graph,) = graphs
    targets = [node.target for node in graph.graph.nodes if node.op == "call_function"]
    assert targets.count(torch.ops.unicorn.filter_matrix.default) == 2  # rows and columns
    assert not {torch.eye, F.pad} & set(targets)

    compiled = torch.compile(lambda x: separable_filter(x, ty, tx, "reflect"), backend="aot_eager", fullgraph=True)
    out = compiled(x)
    torch.testing.assert_close(out, _conv_reference(x.detach(), ty, tx, "reflect"))
    grad = torch.autograd.grad(out.square().sum(), x)[0]
    y = x.detach().requires_grad_(True)
    expected = torch.autograd.grad(_conv_reference(y, ty, tx, "reflect").square().sum(), y)[0]
    torch.testing.assert_close(grad, expected)
    torch._dynamo.reset()
