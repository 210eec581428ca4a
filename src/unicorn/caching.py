"""A memoising decorator that ``torch.compile`` traces through.

Small pure helpers (a shape contract's parse, a filter's taps or matrix) are cached because a training step calls
them many times. Under ``torch.compile`` a cache hit is wrong twice over: dynamo cannot look into
``functools.lru_cache`` (it warns and breaks the graph), and a tensor taken from the cache would enter the graph as
a constant captured from outside. So, while compiling, the function is run as written and the compiled graph holds
its result.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import torch

__all__ = ["cache_outside_compile"]

F = TypeVar("F", bound=Callable[..., Any])


def cache_outside_compile(maxsize: int | None = 128) -> Callable[[F], F]:
    """``functools.lru_cache(maxsize)`` for eager calls; an uncached call while ``torch.compile`` traces.

    The decorated function keeps ``cache_clear`` and ``cache_info`` of the eager cache and ``__wrapped__`` (the
    function as written). Arguments must be hashable, as for ``lru_cache``.
    """

    def decorate(fn: F) -> F:
        cached = functools.lru_cache(maxsize=maxsize)(fn)

        @functools.wraps(fn)
        def call(*args: Any, **kwargs: Any) -> Any:
            if torch.compiler.is_compiling():
                return fn(*args, **kwargs)
            return cached(*args, **kwargs)

        call.cache_clear = cached.cache_clear  # type: ignore[attr-defined]
        call.cache_info = cached.cache_info  # type: ignore[attr-defined]
        return call  # type: ignore[return-value]

    return decorate
