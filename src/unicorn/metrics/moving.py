"""Exact nearest neighbours of a 3D point cloud that moves a little between searches, such as an ICP's source.

An ICP searches, at every iteration, the nearest target point of each source point and the nearest source point
of each target point, while the source moves by small steps. :class:`MovingQueries` gives the same answers as
the k-d trees of :class:`~unicorn.metrics.nn.NearestNeighborIndex` from the previous step's answers and uniform
grids, after one tree search at the first step:

- source to target: each source point keeps the ``k`` nearest target points found for it last (its candidates),
  the distance ``d_k`` of the farthest of them and the position it was found from. When the point has moved by
  ``delta`` since, no target point outside its candidates is nearer than ``d_k - delta`` (triangle inequality):
  if the nearest candidate is nearer than that, it is the nearest target point. Otherwise the ``k`` nearest are
  found again among the target points of the grid cells within the distance of the farthest old candidate,
  which holds at least ``k`` points;
- target to source: each target point keeps the source point nearest to it at the last step. That point's
  distance now bounds the nearest one's, so the nearest is found among the source points of the grid cells
  (a grid over the moved source, built at every step) within that distance.

The distances are computed in float64 and the tests and cell ranges carry a relative margin of ``1e-12``, so
rounding can only make a search wider. The answers have the k-d tree's nearest distances, and its indices
except where two points are exactly as near (then either may be returned). Clouds that are not 3D, and the
torch backend, are searched by the index as it is.
"""

from __future__ import annotations

import os
from typing import Any

import numba
import numpy as np
import torch

from .nn import NearestNeighborIndex

__all__ = ["MovingQueries"]

if "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # OpenMP first (as torch and pykdtree use): numba's default tries TBB first and warns when an installed TBB is
    # too old for it
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

#: relative margin of the distance tests and of the scanned cell ranges
_MARGIN = 1e-12
#: query chunks of a kernel call, shared out among the threads (each allocates its scratch once)
_CHUNKS = 64


def _cells(n: int) -> int:
    """Grid cells per axis for ``n`` surface points: about 8 points per occupied cell (6 x cells^2 of them)."""
    return int(min(max(np.sqrt(n / 48.0), 2), 96))


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
    for key in range(cells**3):
        start[key + 1] += start[key]
    fill = start[:-1].copy()
    members = np.empty(len(cloud), np.int64)
    for i in range(len(cloud)):
        members[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return lo, inv, start, members


@numba.njit(cache=True, nogil=True)
def _cell_range(q: np.ndarray, r: float, lo: np.ndarray, inv: float, cells: int, first: np.ndarray, last: np.ndarray):
    """The cells (``first`` to ``last`` per axis, (3,) each) of a grid that overlap the cube around the ball of
    radius ``r`` at ``q`` (3,), the radius widened by the margin."""
    r = r * (1.0 + _MARGIN) + _MARGIN
    for c in range(3):
        first[c] = min(max(int(np.floor((q[c] - r - lo[c]) * inv)), 0), cells - 1)
        last[c] = min(max(int(np.floor((q[c] + r - lo[c]) * inv)), 0), cells - 1)


@numba.njit(cache=True, nogil=True)
def _dist2(a: np.ndarray, b: np.ndarray) -> float:
    d = 0.0
    for c in range(3):
        t = a[c] - b[c]
        d += t * t
    return d


@numba.njit(cache=True, nogil=True)
def _gap2(t: float, cell: int, side: float) -> float:
    """A lower bound of the squared distance along one axis from a query at ``t`` (in cell sides from the grid's
    corner) to the members of cell ``cell``: the gap is shortened by 1e-9 of a side, far more than the rounding
    of the members' cell assignment."""
    g = max(cell - t, t - (cell + 1), 0.0) - 1e-9
    return g * g * side * side if g > 0.0 else 0.0


@numba.njit(cache=True, nogil=True)
def _scan(q, cloud, grid, cells, r, best_d, best_j, work) -> None:
    """Insert the points of ``cloud`` in the grid cells within ``r`` of ``q`` into the sorted lists ``best_d``
    (squared distances, (k,)) and ``best_j`` (rows) of the k nearest found so far. ``work``: (2, 3) int64
    scratch, allocated once per kernel call (an allocation per query costs more than the scan).

    The cells are visited in key order; each row of cells (first two cell coordinates fixed) is narrowed to the
    cells within the k-th distance found so far, or skipped. The points left out could not have entered the lists
    (the bounds carry the relative margin), so the answers are those of a scan of every cell in range, ties
    included."""
    lo, inv, start, members = grid
    first, last = work[0], work[1]
    _cell_range(q, r, lo, inv, cells, first, last)
    k = len(best_d)
    # the k-th squared distance, widened: no point farther than it can enter the lists
    limit = best_d[k - 1] * (1.0 + _MARGIN)
    side = 1.0 / inv if inv > 0.0 else 0.0  # a cloud of one point: a single cell, no gaps
    t0, t1 = (q[0] - lo[0]) * inv, (q[1] - lo[1]) * inv
    for a in range(first[0], last[0] + 1):
        gap_a = _gap2(t0, a, side)
        if gap_a > limit:
            continue
        for b in range(first[1], last[1] + 1):
            gap_ab = gap_a + _gap2(t1, b, side)
            if gap_ab > limit:
                continue
            e0, e1 = first[2], last[2]
            if gap_ab > 0.0:
                # a row off the query's: its cells within what is left of the k-th distance, widened as in
                # _cell_range (the query's own rows keep the whole range: narrowing them costs more than it saves)
                rest = np.sqrt(limit - gap_ab) * (1.0 + _MARGIN) + _MARGIN
                e0 = max(int(np.floor((q[2] - rest - lo[2]) * inv)), e0)
                e1 = min(int(np.floor((q[2] + rest - lo[2]) * inv)), e1)
                if e0 > e1:
                    continue
            row = (a * cells + b) * cells
            for m in range(start[row + e0], start[row + e1 + 1]):
                j = members[m]
                d = _dist2(q, cloud[j])
                if d < best_d[k - 1]:
                    pos = k - 1
                    while pos > 0 and best_d[pos - 1] > d:
                        best_d[pos], best_j[pos] = best_d[pos - 1], best_j[pos - 1]
                        pos -= 1
                    best_d[pos], best_j[pos] = d, j
                    limit = best_d[k - 1] * (1.0 + _MARGIN)


@numba.njit(cache=True, nogil=True, parallel=True)
def _follow(queries, points, grid, cells, anchors, reach, candidates, out, every) -> None:
    """Source to target (module docstring): for each query (N, 3) its nearest row of ``points`` (U, 3) into
    ``out`` (N,), updating the ``anchors`` (N, 3), ``reach`` (N,) (``d_k``; inf when ``every`` point is a
    candidate) and ``candidates`` (N, k) of the queries found again."""
    n, k = len(queries), candidates.shape[1]
    for chunk in numba.prange(_CHUNKS):
        best_d, best_j, work = np.empty(k), np.empty(k, np.int64), np.empty((2, 3), np.int64)
        for i in range(chunk * n // _CHUNKS, (chunk + 1) * n // _CHUNKS):
            q = queries[i]
            near, near_j, far = np.inf, -1, 0.0
            for m in range(k):
                d = _dist2(q, points[candidates[i, m]])
                if d < near:
                    near, near_j = d, candidates[i, m]
                far = max(far, d)
            bound = reach[i] - np.sqrt(_dist2(q, anchors[i]))
            if bound > 0.0 and np.sqrt(near) <= bound * (1.0 - _MARGIN):
                out[i] = near_j
                continue
            # the ball through the farthest old candidate holds k points, hence the k nearest
            best_d[:] = far * (1.0 + _MARGIN) + _MARGIN
            best_j[:] = -1
            _scan(q, points, grid, cells, np.sqrt(far), best_d, best_j, work)
            anchors[i] = q
            reach[i] = np.inf if every else np.sqrt(best_d[k - 1])
            candidates[i] = best_j
            out[i] = best_j[0]


@numba.njit(cache=True, nogil=True, parallel=True)
def _nearest_from(cloud, grid, cells, queries, guess, out) -> None:
    """Target to source (module docstring): for each query (U, 3) the row of ``cloud`` (N, 3) nearest to it into
    ``out`` (U,), found within the distance of its ``guess`` (U,)."""
    n = len(queries)
    for chunk in numba.prange(_CHUNKS):
        best_d, best_j, work = np.empty(1), np.empty(1, np.int64), np.empty((2, 3), np.int64)
        for i in range(chunk * n // _CHUNKS, (chunk + 1) * n // _CHUNKS):
            best_d[0] = _dist2(queries[i], cloud[guess[i]])
            best_j[0] = guess[i]
            _scan(queries[i], cloud, grid, cells, np.sqrt(best_d[0]), best_d, best_j, work)
            out[i] = best_j[0]


@numba.njit(cache=True, nogil=True, parallel=True)
def _take(cloud, order, out) -> None:
    """``out[i] = cloud[order[i]]``: the rows of ``cloud`` (N, 3) in visiting ``order`` (N,) into ``out`` (N, 3)
    float64 (exact from float32), in one pass (numpy's cast then row gather take 5x longer)."""
    n = len(order)
    for chunk in numba.prange(_CHUNKS):
        for i in range(chunk * n // _CHUNKS, (chunk + 1) * n // _CHUNKS):
            for c in range(3):
                out[i, c] = cloud[order[i], c]


def _use_torch_threads() -> None:
    """Run the kernels on as many threads as torch (``OMP_NUM_THREADS``, ``torch.set_num_threads``) uses."""
    threads = torch.get_num_threads()
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    if torch.get_num_threads() != threads:
        # starting numba's OpenMP pool (at its first use) sets the OpenMP thread count it shares with torch to
        # all of numba's threads: torch would then run on every core whatever OMP_NUM_THREADS says
        torch.set_num_threads(threads)


class _TrackedTree:
    """Source-to-target searches of one moving cloud in the fixed (U, 3) float64 ``points`` of a k-d ``tree``
    (which finds the first step's candidates) and of a grid built here."""

    def __init__(self, tree: Any, points: np.ndarray, k: int) -> None:
        self.tree, self.points = tree, points
        self.k = min(k, len(points))
        self.every = self.k == len(points)  # no point can lie outside the candidates
        self.cells = _cells(len(points))
        self.grid = _grid(points, self.cells)
        self.anchors: np.ndarray | None = None

    def nearest(self, queries: np.ndarray) -> np.ndarray:
        """(N,) int64 rows of ``points`` nearest to ``queries`` (N, 3) float64 (the same N points every call)."""
        if self.anchors is None or self.anchors.shape != queries.shape:
            dists, self.candidates = self.tree.knearest(queries, self.k)
            self.anchors = queries.copy()
            self.reach = np.full(len(queries), np.inf) if self.every else dists[:, -1].copy()
            return self.candidates[:, 0].copy()
        out = np.empty(len(queries), dtype=np.int64)
        _follow(queries, self.points, self.grid, self.cells, self.anchors, self.reach, self.candidates, out, self.every)
        return out


class _TrackedCloud:
    """Target-to-source searches into one moving cloud: the first step (or a cloud of another size) by
    ``fallback`` (a k-d tree over the cloud), then by a grid over the cloud from the last step's answers."""

    def __init__(self, fallback: Any) -> None:
        self.fallback = fallback
        self.guess: np.ndarray | None = None  # rows of a cloud of ``size`` points
        self.size = 0

    def nearest_in(self, cloud: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """(U,) int64 rows of ``cloud`` (N, 3) float64 nearest to ``queries`` (U, 3) float64 (the same N points,
        moved, and the same queries every call)."""
        if self.guess is None or len(cloud) != self.size:
            found = self.fallback.nearest_in(cloud, queries)
        else:
            cells = _cells(len(cloud))
            found = np.empty(len(queries), dtype=np.int64)
            _nearest_from(cloud, _grid(cloud, cells), cells, queries, self.guess, found)
        self.guess, self.size = found, len(cloud)
        return found


class MovingQueries:
    """The searches of a query cloud ``x`` (B, N, D) that moves a little between calls (an ICP's source) against
    an index's fixed clouds ``y``, in both directions: :meth:`query` as :meth:`NearestNeighborIndex.query` and
    :meth:`reverse_query` as :meth:`NearestNeighborIndex.reverse_query`, with the same answers.

    Every call must pass the same B x N points (moved) and the same ``order``. :meth:`query` keeps each point's
    candidates (module docstring); :meth:`reverse_query` starts each point of ``y`` from the point of ``x``
    nearest to it at the last call and scans a uniform grid over ``x`` around it (the first call builds a k-d tree
    over ``x``). Clouds that are not 3D, and the torch backend, go to the index unchanged.

    Args:
        index: the index over the fixed reference clouds ``y`` (B, M, D).
        k: candidates kept per query point: more make the grid searches rarer and each one slower (8 suits an
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
        trees = index.trees() if index.y.shape[-1] == 3 else None
        self._distinct = None if trees is None else [distinct for _, distinct in trees]
        self._forward = None if trees is None else [_TrackedTree(tree, d.points, k) for tree, d in trees]
        self._reverse = None if trees is None else [_TrackedCloud(index.tree_builder()) for _ in trees]
        self._moved: list[np.ndarray] = []  # per cloud of x, its float64 points in visiting order (reused)

    @torch.no_grad()
    def indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Indices (B, N) long into ``y`` of the nearest neighbours of ``x`` (B, N, D); ``order`` as
        :meth:`NearestNeighborIndex.indices`."""
        return self._search(x, order, forward=True, reverse=False)[0]

    @torch.no_grad()
    def reverse_indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Indices (B, M) long into ``x`` (B, N, D) of the nearest neighbours of ``y``; ``order`` as
        :meth:`NearestNeighborIndex.indices`."""
        return self._search(x, order, forward=False, reverse=True)[1]

    @torch.no_grad()
    def both_indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`indices` (B, N) and :meth:`reverse_indices` (B, M) of ``x`` (B, N, D) in one call, which reads
        ``x`` once for both (a Chamfer distance's searches)."""
        return self._search(x, order, forward=True, reverse=True)

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

    def _search(
        self, x: torch.Tensor, order: torch.Tensor | None, forward: bool, reverse: bool
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """The searches asked for: (B, N) indices into ``y`` and (B, M) indices into ``x`` (None when not asked).
        Each cloud of ``x`` is read once into a float64 buffer in visiting order, which both directions search."""
        orders = self.index.visiting_orders(x, order)
        if self._forward is None or self._reverse is None or self._distinct is None or orders is None:
            return (
                self.index.indices(x, order) if forward else None,
                self.index.reverse_indices(x, order) if reverse else None,
            )
        _use_torch_threads()
        B, N = x.shape[:2]
        if len(self._moved) != B or self._moved[0].shape[0] != N:
            self._moved = [np.empty((N, 3)) for _ in range(B)]
        points = x.detach().cpu()
        if points.dtype not in (torch.float32, torch.float64):
            points = points.double()  # the kernels read float32 and float64 only
        found_y, found_x = [], []
        for b, xb in enumerate(points.numpy()):
            ob = np.arange(N) if orders[b] is None else orders[b]
            moved, distinct = self._moved[b], self._distinct[b]
            _take(xb, ob, moved)
            if forward:
                rows = np.empty(N, dtype=np.int64)
                rows[ob] = distinct.first[self._forward[b].nearest(moved)]
                found_y.append(torch.from_numpy(rows))
            if reverse:
                found_x.append(
                    torch.from_numpy(ob[self._reverse[b].nearest_in(moved, distinct.points)][distinct.inverse])
                )
        return (
            torch.stack(found_y).to(x.device) if forward else None,
            torch.stack(found_x).to(x.device) if reverse else None,
        )
