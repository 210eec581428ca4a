"""Exact nearest neighbours of a point cloud that moves a little between searches, such as an ICP's source.

An ICP searches the nearest ground-truth point of each source point at every iteration, while the source moves
by small steps. :class:`MovingQueries` gives the same answers with far fewer k-d tree searches. Each query point
keeps the ``k`` nearest reference points that its last tree search found (its candidates), the distance ``d_k``
of the farthest of them, and the position it was searched from. When the point has moved by ``delta`` since, no
reference point outside its candidates is nearer than ``d_k - delta`` (triangle inequality). So when the nearest
candidate is nearer than that, it is the nearest reference point, and only the points that fail this test are
searched again. Both tests are computed in float64 with a relative margin of ``1e-12``, so rounding can only send
a point back to the tree.

The answers are the k-d tree's: the same nearest distances, and the same indices except where two reference
points are exactly as near (then either may be returned). With the torch backend (CUDA) the queries go to the
index unchanged.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch

from .nn import NearestNeighborIndex

__all__ = ["MovingQueries"]

#: relative margin of the candidate test: a point whose test is closer than this is searched in the tree again
_MARGIN = 1e-12


@numba.njit(cache=True, nogil=True)
def _nearest_candidates(
    queries: np.ndarray,
    points: np.ndarray,
    anchors: np.ndarray,
    reach: np.ndarray,
    candidates: np.ndarray,
    out: np.ndarray,
) -> np.ndarray:
    """For each query (N, D), its nearest candidate (``candidates`` (N, k) rows into ``points`` (U, D)) into
    ``out`` (N,) where the test of the module docstring proves it the nearest point; returns the (F,) rows of
    the queries that fail (``anchors`` (N, D): where each was last searched, ``reach`` (N,): its ``d_k``)."""
    n, dim = queries.shape
    failed = np.empty(n, np.int64)
    n_failed = 0
    for i in range(n):
        moved = 0.0
        for c in range(dim):
            t = queries[i, c] - anchors[i, c]
            moved += t * t
        best, best_j = np.inf, -1
        for m in range(candidates.shape[1]):
            j = candidates[i, m]
            d = 0.0
            for c in range(dim):
                t = queries[i, c] - points[j, c]
                d += t * t
            if d < best:
                best, best_j = d, j
        bound = reach[i] - np.sqrt(moved)
        if bound > 0.0 and np.sqrt(best) <= bound * (1.0 - _MARGIN):
            out[i] = best_j
        else:
            failed[n_failed] = i
            n_failed += 1
    return failed[:n_failed]


@numba.njit(cache=True, nogil=True)
def _grid(cloud: np.ndarray, cells: int) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """A uniform grid of ``cells``^3 cubic cells over the bounding cube of ``cloud`` (N, 3): its corner (3,), the
    inverse cell side, the (cells^3 + 1,) offsets of each cell's members and the (N,) members, cell by cell."""
    lo = np.empty(3)
    extent = 0.0
    for c in range(3):
        lo[c] = cloud[:, c].min()
        extent = max(extent, cloud[:, c].max() - lo[c])
    inv = cells / extent if extent > 0.0 else 0.0
    cell = np.empty(len(cloud), np.int64)
    start = np.zeros(cells**3 + 1, np.int64)
    for i in range(len(cloud)):
        key = 0
        for c in range(3):
            key = key * cells + min(int((cloud[i, c] - lo[c]) * inv), cells - 1)
        cell[i] = key
        start[key + 1] += 1
    for k in range(cells**3):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    members = np.empty(len(cloud), np.int64)
    for i in range(len(cloud)):
        members[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return lo, inv, start, members


@numba.njit(cache=True, nogil=True)
def _grid_nearest(
    cloud: np.ndarray,
    cells: int,
    grid: tuple[np.ndarray, float, np.ndarray, np.ndarray],
    queries: np.ndarray,
    guess: np.ndarray,
    out: np.ndarray,
) -> None:
    """For each query (U, 3), the row of ``cloud`` (N, 3) nearest to it into ``out`` (U,): the nearest point of the
    grid cells that overlap the ball through its ``guess`` (U,) (the nearest point lies in that ball)."""
    lo, inv, start, members = grid
    first = np.empty(3, np.int64)
    last = np.empty(3, np.int64)
    for i in range(len(queries)):
        g = guess[i]
        best = 0.0
        for c in range(3):
            t = queries[i, c] - cloud[g, c]
            best += t * t
        # the ball's radius, widened so that rounding cannot leave its nearest point's cell out
        r = np.sqrt(best) * (1.0 + _MARGIN) + _MARGIN
        for c in range(3):
            first[c] = min(max(int(np.floor((queries[i, c] - r - lo[c]) * inv)), 0), cells - 1)
            last[c] = min(max(int(np.floor((queries[i, c] + r - lo[c]) * inv)), 0), cells - 1)
        best_j = g
        for a in range(first[0], last[0] + 1):
            for b in range(first[1], last[1] + 1):
                for e in range(first[2], last[2] + 1):
                    key = (a * cells + b) * cells + e
                    for m in range(start[key], start[key + 1]):
                        j = members[m]
                        d = 0.0
                        for c in range(3):
                            t = queries[i, c] - cloud[j, c]
                            d += t * t
                        if d < best:
                            best, best_j = d, j
        out[i] = best_j


class _TrackedTree:
    """One k-d tree (``tree.knearest``) over (U, D) float64 ``points`` and the candidates of one moving cloud."""

    def __init__(self, tree: Any, points: np.ndarray, k: int) -> None:
        self.tree, self.points = tree, points
        self.k = min(k, len(points))
        self.anchors = np.empty((0, points.shape[1]))
        self.reach = np.empty(0)
        self.candidates = np.empty((0, self.k), dtype=np.int64)

    def nearest(self, queries: np.ndarray) -> np.ndarray:
        """(N,) int64 rows of ``points`` nearest to ``queries`` (N, D) float64 (the same N points every call)."""
        n = len(queries)
        if self.anchors.shape != queries.shape:  # the first call: every point is searched
            self.anchors = np.empty_like(queries)
            self.reach = np.full(n, -1.0)
            self.candidates = np.zeros((n, self.k), dtype=np.int64)
        out = np.empty(n, dtype=np.int64)
        failed = _nearest_candidates(queries, self.points, self.anchors, self.reach, self.candidates, out)
        if len(failed):
            dists, idx = self.tree.knearest(queries[failed], self.k)
            self.anchors[failed] = queries[failed]
            # when the candidates are all the points, none can be outside them
            self.reach[failed] = dists[:, -1] if self.k < len(self.points) else np.inf
            self.candidates[failed] = idx
            out[failed] = idx[:, 0]
        return out


class _TrackedCloud:
    """Reverse searches into one moving cloud: each fixed query starts from the cloud point nearest to it at the
    last call (the same points, moved: its distance bounds the nearest one's) and scans the cells of a uniform
    grid over the cloud within that distance. The first call, and clouds that are not 3D, use ``fallback``."""

    def __init__(self, fallback: Any) -> None:
        self.fallback = fallback
        self.guess: np.ndarray | None = None

    def nearest_in(self, cloud: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """(U,) int64 rows of ``cloud`` (N, 3) float64 nearest to ``queries`` (U, 3) float64 (the same N points,
        moved, and the same queries every call)."""
        if self.guess is None or cloud.shape[1] != 3 or self.guess.max(initial=-1) >= len(cloud):
            found = self.fallback.nearest_in(cloud, queries)
        else:
            # about 8 points per occupied cell on a surface (6 x cells^2 occupied cells)
            cells = int(min(max(np.sqrt(len(cloud) / 48.0), 2), 96))
            found = np.empty(len(queries), dtype=np.int64)
            _grid_nearest(cloud, cells, _grid(cloud, cells), queries, self.guess, found)
        self.guess = found
        return found


class MovingQueries:
    """The searches of a query cloud ``x`` (B, N, D) that moves a little between calls (an ICP's source) against
    an index's fixed clouds ``y``, in both directions: :meth:`query` as :meth:`NearestNeighborIndex.query` and
    :meth:`reverse_query` as :meth:`NearestNeighborIndex.reverse_query`, with the same answers.

    Every call must pass the same B x N points (moved) and the same ``order``. :meth:`query` keeps each point's
    candidates (module docstring); :meth:`reverse_query` starts each point of ``y`` from the point of ``x``
    nearest to it at the last call and scans a uniform grid over ``x`` around it (3D clouds; others, and the
    first call, build a k-d tree over ``x``). With the torch backend both go to the index unchanged.

    Args:
        index: the index over the fixed reference clouds ``y`` (B, M, D).
        k: candidates kept per query point: more make the tree searches rarer and each one slower (8 suits an
            ICP's steps on clouds of 3k to 100k surface points).

    Example:
        >>> y = torch.rand(1, 500, 3)
        >>> index, moving = NearestNeighborIndex(y), MovingQueries(NearestNeighborIndex(y))
        >>> x = [torch.rand(1, 200, 3) + s for s in (0, 1e-3, 2e-3)]
        >>> all(torch.equal(moving.indices(xi), index.indices(xi)) for xi in x)
        True
        >>> all(torch.equal(moving.reverse_indices(xi), index.reverse_indices(xi)) for xi in x)
        True
    """

    def __init__(self, index: NearestNeighborIndex, k: int = 8) -> None:
        if k < 1:
            raise ValueError(f"k must be positive, got {k}")
        self.index = index
        trees = index.trees()
        self._forward = None if trees is None else [_TrackedTree(tree, points, k) for tree, points in trees]
        self._reverse = None if trees is None else [_TrackedCloud(index.tree_builder()) for _ in trees]

    @torch.no_grad()
    def indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Indices (B, N) long into ``y`` of the nearest neighbours of ``x`` (B, N, D); ``order`` as
        :meth:`NearestNeighborIndex.indices`."""
        return self.index.search(x, order, self._forward)

    @torch.no_grad()
    def reverse_indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Indices (B, M) long into ``x`` (B, N, D) of the nearest neighbours of ``y``; ``order`` as
        :meth:`NearestNeighborIndex.indices`."""
        return self.index.reverse_search(x, order, self._reverse)

    def query(self, x: torch.Tensor, order: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances (B, N), differentiable w.r.t. ``x`` and ``y``, and indices (B, N), as
        :meth:`NearestNeighborIndex.query`."""
        idx = self.indices(x, order)
        return self.index.distances(x, idx), idx

    def reverse_query(self, x: torch.Tensor, order: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances (B, M), differentiable w.r.t. ``x`` and ``y``, and indices (B, M) into ``x``, as
        :meth:`NearestNeighborIndex.reverse_query`."""
        idx = self.reverse_indices(x, order)
        return self.index.reverse_distances(x, idx), idx
