"""unicorn.caching: an lru_cache for eager calls that torch.compile traces through."""

from __future__ import annotations

import warnings

import pytest
import torch

from unicorn.caching import cache_outside_compile
from unicorn.checks import check_shape
from unicorn.model.filtering import filter_matrix


def _counted_taps():
    calls: list[int] = []

    @cache_outside_compile(maxsize=4)
    def taps(n: int) -> torch.Tensor:
        calls.append(n)
        return torch.arange(n, dtype=torch.float32)

    return taps, calls


def test_eager_calls_are_cached():
    taps, calls = _counted_taps()
    first = taps(3)
    assert taps(3) is first  # the same tensor, built once
    assert calls == [3]
    assert taps.cache_info().hits == 1
    taps(5)
    assert calls == [3, 5]
    taps.cache_clear()
    taps(3)
    assert calls == [3, 5, 3]
    assert taps.__wrapped__(2).tolist() == [0.0, 1.0]  # the function as written


def test_compiled_callers_trace_the_function_in_one_graph():
    taps, calls = _counted_taps()
    taps(3)  # in the eager cache before compiling

    def scaled(x: torch.Tensor) -> torch.Tensor:
        return x * taps(3).sum()

    compiled = torch.compile(scaled, backend="eager", fullgraph=True)  # fullgraph: a graph break raises
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # dynamo warns when it meets an lru_cache wrapper
        out = compiled(torch.ones(2))
    assert out.tolist() == [3.0, 3.0]
    assert calls == [3, 3]  # run while tracing, not looked up
    torch._dynamo.reset()


def _checked(x: torch.Tensor) -> torch.Tensor:
    check_shape(x, "B, 3", "x")
    return x * 2


def _filtered(x: torch.Tensor) -> torch.Tensor:
    return filter_matrix(3, [0.25, 0.5, 0.25], "reflect", x) @ x


@pytest.mark.parametrize("caller", [_checked, _filtered], ids=["check_shape", "filter_matrix"])
def test_the_package_cached_helpers_compile_without_warnings(caller):
    x = torch.rand(3, 3)
    compiled = torch.compile(caller, backend="eager", fullgraph=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        torch.testing.assert_close(compiled(x), caller(x))
    torch._dynamo.reset()
