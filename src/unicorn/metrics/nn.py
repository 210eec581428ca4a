"""Exact nearest-neighbour search between point clouds in bounded memory.

The backends find the neighbour indices without gradient; the distances are then recomputed in torch from the
matched pairs, so they are exact (no ``|x|^2 - 2 x.y + |y|^2`` cancellation) and differentiable with respect
to both clouds.

- ``"pykdtree"``: :mod:`pykdtree` k-d trees on the CPU (float64, ``OMP_NUM_THREADS`` threads). The default when it
  is installed, for CPU and CUDA tensors alike: CUDA clouds are copied to the CPU and the indices back.
- ``"kdtree"``: :class:`scipy.spatial.cKDTree` on the CPU (float64), the default otherwise (``bm_eval.py`` compares).
- ``"torch"``: brute force on the tensors' device, in blocks of at most ``block_elements`` pairwise distances (a
  running minimum over blocks of ``y``), so memory stays bounded whatever the cloud sizes, each distance from the
  coordinate differences (the neighbours the k-d trees find, up to float32 rounding of near-ties). No host round
  trip, but quadratic: ``benchmarks/bm_metrics.py --device cuda`` compares it with the trees.

:class:`NearestNeighborIndex` holds a fixed reference cloud (a ground truth) and answers both directions of a
Chamfer distance against clouds that change (an ICP's moving source): the nearest reference point of each
query point (:meth:`~NearestNeighborIndex.query`) and the nearest query point of each reference point
(:meth:`~NearestNeighborIndex.reverse_query`). The k-d tree backends search each distinct reference point once
(ground-truth clouds stored in float16, as ShapeNet's are, repeat many points) and break ties between copies of
a point by taking its first occurrence.

The queries take an optional visiting order: in :func:`spatial_order` (a Z-order curve) consecutive queries walk
the same branches of a tree (``docs/performance.md``, "Evaluation"). A cloud queried many times under a similarity
transform (an ICP's source) keeps one order; the reference clouds' distinct points are kept in that order.
"""

from __future__ import annotations

import copy
import importlib.util
from typing import Literal, NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from unicorn.checks import check_points, check_same_batch, check_shape

__all__ = [
    "BACKENDS",
    "Backend",
    "NearestNeighborIndex",
    "default_backend",
    "gather_points",
    "nearest_neighbors",
    "spatial_order",
]

Backend = Literal["auto", "kdtree", "pykdtree", "torch"]


def gather_points(y: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Pick ``y[b, idx[b, n]]``: y (B, M, D), idx (B, N) long -> (B, N, D)."""
    if not y.is_contiguous():
        return torch.gather(y, 1, idx.unsqueeze(-1).expand(-1, -1, y.shape[-1]))
    # whole rows of the flattened batch: twice as fast as a gather of each coordinate
    B, M, D = y.shape
    rows = idx + torch.arange(0, B * M, M, device=idx.device).unsqueeze(1)
    return y.view(B * M, D).index_select(0, rows.view(-1)).view(B, -1, D)


#: bits per axis of the Z-order codes of :func:`spatial_order` (3 x 10 bits: 1024 cells per axis)
_MORTON_BITS = 10


def _spread_bits(v: torch.Tensor) -> torch.Tensor:
    """Integers < 2**10 (int64) with two zero bits after each bit, so that three of them interleave."""
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    return (v | (v << 2)) & 0x09249249


@torch.no_grad()
def spatial_order(points: torch.Tensor) -> torch.Tensor:
    """Permutations (B, N) long putting each cloud of ``points`` (B, N, D) in Z-order (Morton order).

    Nearby points get nearby ranks (the first three coordinates, 1024 cells per axis over each cloud's bounding
    cube), and stay so under a similarity transform of the cloud. It only changes how fast the k-d trees answer,
    never which neighbours they find.
    """
    check_points(points, "points", dim=None)
    p = points.detach()[..., :3]
    lo = p.amin(dim=1, keepdim=True)
    extent = (p.amax(dim=1, keepdim=True) - lo).amax(dim=-1, keepdim=True)
    top = 2**_MORTON_BITS - 1
    cells = ((p - lo) * (top / extent.clamp_min(torch.finfo(p.dtype).tiny))).long().clamp(0, top)
    code = torch.zeros(cells.shape[:2], dtype=torch.long, device=p.device)
    for axis in range(cells.shape[-1]):
        code |= _spread_bits(cells[..., axis]) << axis
    return torch.sort(code, dim=1, stable=True).indices


def _squared_distances(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(N, M) squared distances between (N, D) and (M, D) points, summed from the coordinate differences.

    Not the matrix-product form (|x|^2 - 2 x.y + |y|^2): its cancellation picks another neighbour among near-ties
    often enough to move an ICP's result by 1e-4 to 1e-3. One coordinate at a time, in place, rather than
    ``torch.cdist``'s coordinate-difference kernel, which is many times slower on CUDA.
    """
    d = (x[:, None, 0] - y[None, :, 0]).square_()
    for k in range(1, x.shape[1]):
        d.add_((x[:, None, k] - y[None, :, k]).square_())
    return d


def _torch_indices(x: torch.Tensor, y: torch.Tensor, block_elements: int) -> torch.Tensor:
    x, y = x.detach(), y.detach()
    B, N, _ = x.shape
    M = y.shape[1]
    cols = min(M, max(1, int(np.sqrt(block_elements))))
    rows = min(N, max(1, block_elements // cols))
    out = torch.empty(B, N, dtype=torch.long, device=x.device)
    for b in range(B):
        xb, yb = x[b], y[b]
        for r0 in range(0, N, rows):
            xs = xb[r0 : r0 + rows]
            best = torch.full((xs.shape[0],), float("inf"), dtype=x.dtype, device=x.device)
            best_idx = torch.zeros(xs.shape[0], dtype=torch.long, device=x.device)
            for c0 in range(0, M, cols):
                d, j = _squared_distances(xs, yb[c0 : c0 + cols]).min(dim=1)
                better = d < best
                best = torch.where(better, d, best)
                best_idx = torch.where(better, j + c0, best_idx)
            out[b, r0 : r0 + rows] = best_idx
    return out


# ---------------------------------------------------------------------------------------------- CPU k-d trees
class _ScipyTree:
    """A :class:`scipy.spatial.cKDTree` over (M, D) float64 points; ``nearest`` gives (N,) int64 indices,
    ``knearest`` the (N, k) float64 distances and int64 indices of the k nearest, closest first."""

    def __init__(self, points: np.ndarray, workers: int) -> None:
        # sliding-midpoint trees with larger leaves: 3-4x faster than scipy's defaults for queries far
        # from a surface sample (the first ICP iterations), as fast otherwise
        self.tree = cKDTree(points, leafsize=32, balanced_tree=False, compact_nodes=False)
        self.workers = workers

    def nearest(self, queries: np.ndarray) -> np.ndarray:
        return np.asarray(self.tree.query(queries, k=1, workers=self.workers)[1], dtype=np.int64)

    def knearest(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        dists, idx = self.tree.query(queries, k=k, workers=self.workers)
        return np.asarray(dists, dtype=np.float64).reshape(len(queries), k), np.asarray(idx, np.int64).reshape(-1, k)


class _PyKDTree:
    """A :class:`pykdtree.kdtree.KDTree` (OpenMP threads: ``workers`` is not used); same interface."""

    def __init__(self, points: np.ndarray, workers: int) -> None:
        from pykdtree.kdtree import KDTree

        self.tree = KDTree(points, leafsize=16)

    def nearest(self, queries: np.ndarray) -> np.ndarray:
        return self.tree.query(queries, k=1, sqr_dists=True)[1].astype(np.int64)

    def knearest(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        dists, idx = self.tree.query(queries, k=k)
        return np.asarray(dists, dtype=np.float64).reshape(len(queries), k), idx.astype(np.int64).reshape(-1, k)


class _FreshTree:
    """Reverse searches by a tree of class ``tree`` built over each searched cloud."""

    def __init__(self, tree: type[_ScipyTree] | type[_PyKDTree], workers: int) -> None:
        self.tree, self.workers = tree, workers

    def nearest_in(self, cloud: np.ndarray, queries: np.ndarray) -> np.ndarray:
        return self.tree(cloud, self.workers).nearest(queries)


#: CPU k-d tree backends: name -> tree class
_TREES = {"kdtree": _ScipyTree, "pykdtree": _PyKDTree}

#: every backend name accepted besides ``"auto"``
BACKENDS = (*_TREES, "torch")


def default_backend() -> str:
    """``"pykdtree"`` when installed, else ``"kdtree"``: the k-d trees, whatever the clouds' device."""
    return "pykdtree" if importlib.util.find_spec("pykdtree") is not None else "kdtree"


class _DistinctPoints(NamedTuple):
    """The distinct points of a cloud: ``points[inverse] == cloud`` and ``cloud[first] == points``."""

    points: np.ndarray  # (U, D) float64
    first: np.ndarray  # (U,) int64, each distinct point's first occurrence in the cloud
    inverse: np.ndarray  # (M,) int64


def _distinct(cloud: torch.Tensor) -> _DistinctPoints:
    """The distinct points of ``cloud`` (M, D), in Z-order (they are the reverse direction's queries)."""
    points = np.ascontiguousarray(cloud.detach().to(device="cpu", dtype=torch.float64).numpy())
    # rows compared as 24-byte strings: 5x faster than np.unique(axis=0)
    rows = points.view(np.dtype((np.void, points.dtype.itemsize * points.shape[1]))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    order = spatial_order(torch.from_numpy(points[first][None]))[0].numpy()
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    first = first[order]
    return _DistinctPoints(points[first], first.astype(np.int64), rank[inverse.reshape(-1)].astype(np.int64))


def _in_order(cloud: np.ndarray, order: np.ndarray | None) -> np.ndarray:
    """The rows of ``cloud`` in visiting ``order`` (None: as they are)."""
    return cloud if order is None else cloud[order]


def _rows_as_given(rows: np.ndarray, order: np.ndarray | None) -> np.ndarray:
    """Rows of a cloud taken in ``order`` (:func:`_in_order`) as rows of the cloud as given."""
    return rows if order is None else order[rows]


def _numpy64(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to(device="cpu", dtype=torch.float64).numpy())


class NearestNeighborIndex:
    """A reusable search structure over reference clouds ``y`` (B, M, D), for repeated queries in both directions.

    With the k-d tree backends the trees over ``y`` are built once here, which is what an optimisation loop with
    a fixed target (ICP) or several scorings against one ground truth want.

    Args:
        y: (B, M, D) float reference points.
        backend: ``"pykdtree"``, ``"kdtree"``, ``"torch"`` or ``"auto"``, see :func:`nearest_neighbors`.
        block_elements: torch backend only, the largest number of pairwise distances held at once.
        workers: ``"kdtree"`` backend only, query threads (-1 for all cores).
    """

    def __init__(
        self,
        y: torch.Tensor,
        *,
        backend: Backend = "auto",
        block_elements: int | None = None,
        workers: int = 1,
    ) -> None:
        check_points(y, "y", dim=None)
        if backend == "auto":
            backend = default_backend()  # type: ignore[assignment]
        if backend not in BACKENDS:
            raise ValueError(f"backend must be 'auto' or one of {BACKENDS}, got {backend!r}")
        if block_elements is None:
            block_elements = 2**26 if y.device.type == "cuda" else 2**22
        if block_elements < 1:
            raise ValueError(f"block_elements must be positive, got {block_elements}")
        self.y = y
        self.backend = backend
        self.block_elements = int(block_elements)
        self.workers = workers
        self._distinct: list[_DistinctPoints] | None = None
        self._trees: list | None = None
        if backend in _TREES:
            self._distinct = [_distinct(yb) for yb in y]
            self._trees = [_TREES[backend](d.points, workers) for d in self._distinct]

    def select(self, rows: torch.Tensor | list[int]) -> NearestNeighborIndex:
        """The index over ``y[rows]`` (rows: (K,) batch indices), sharing this one's search structures."""
        rows = [int(r) for r in rows]
        out = copy.copy(self)
        out.y = self.y[rows]
        if self._trees is not None and self._distinct is not None:
            out._trees = [self._trees[r] for r in rows]
            out._distinct = [self._distinct[r] for r in rows]
        return out

    def trees(self) -> list[tuple[_ScipyTree | _PyKDTree, _DistinctPoints]] | None:
        """Per cloud of ``y``, its k-d tree and the distinct points the tree holds (the indices its searches return
        point into them; ``first`` maps them to rows of the cloud); None with the torch backend."""
        if self._trees is None or self._distinct is None:
            return None
        return list(zip(self._trees, self._distinct))

    def tree_builder(self) -> _FreshTree | None:
        """The reverse searcher of :meth:`reverse_indices` (a k-d tree built over each searched cloud), None with the
        torch backend."""
        return None if self._trees is None else _FreshTree(_TREES[self.backend], self.workers)

    def visiting_orders(self, x: torch.Tensor, order: torch.Tensor | None) -> list[np.ndarray | None] | None:
        """Check a query cloud ``x`` (B, N, D) and its ``order`` (B, N) (see :meth:`indices`); for the k-d tree
        backends, the visiting order of each of its clouds ((N,) int64 numpy; None: as given), None otherwise.

        Raises:
            ValueError: when ``x`` does not match ``y`` or ``order`` does not match ``x``.
        """
        check_points(x, "x", dim=None)
        check_same_batch(x, self.y, "x", "y")
        if x.shape[-1] != self.y.shape[-1]:
            raise ValueError(f"x and y must have the same point dimension, got {x.shape[-1]} and {self.y.shape[-1]}")
        if self._trees is None:
            return None
        if order is None:
            return [None] * x.shape[0]
        check_shape(order, "B, N", "order", {"B": x.shape[0], "N": x.shape[1]})
        return list(order.to(device="cpu", dtype=torch.long).numpy())

    @torch.no_grad()
    def indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Indices (B, N) long into ``y`` of the nearest neighbours of ``x`` (B, N, D), without gradient.

        ``order``: (B, N) permutations in which the k-d trees visit the points of ``x``, e.g.
        :func:`spatial_order` (None: as given). It changes the speed, not the result; the torch backend ignores it.
        """
        orders = self.visiting_orders(x, order)
        if self._trees is None or self._distinct is None or orders is None:
            return _torch_indices(x, self.y.to(x.dtype), self.block_elements)
        out = []
        for xb, d, tree, ob in zip(x, self._distinct, self._trees, orders):
            found = d.first[tree.nearest(_in_order(_numpy64(xb), ob))]
            if ob is not None:
                found[ob] = found.copy()
            out.append(torch.from_numpy(found))
        return torch.stack(out).to(x.device)

    @torch.no_grad()
    def reverse_indices(self, x: torch.Tensor, order: torch.Tensor | None = None) -> torch.Tensor:
        """Indices (B, M) long into ``x`` (B, N, D) of the nearest neighbours of ``y``, without gradient.

        The k-d tree backends build a tree over each cloud of ``x``, its points taken in ``order`` (as in
        :meth:`indices`), and query the distinct points of ``y``.
        """
        orders = self.visiting_orders(x, order)
        if self._trees is None or self._distinct is None or orders is None:
            return _torch_indices(self.y.to(x.dtype), x, self.block_elements)
        builder = self.tree_builder()
        assert builder is not None  # k-d tree backends only here
        out = [
            torch.from_numpy(_rows_as_given(builder.nearest_in(_in_order(_numpy64(xb), ob), d.points), ob)[d.inverse])
            for xb, d, ob in zip(x, self._distinct, orders)
        ]
        return torch.stack(out).to(x.device)

    def query(self, x: torch.Tensor, order: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """For each point of ``x`` (B, N, D): distances (B, N), differentiable w.r.t. ``x`` and ``y``, and indices
        (B, N) into ``y`` of its nearest neighbour (``order``: see :meth:`indices`)."""
        idx = self.indices(x, order)
        return self.distances(x, idx), idx

    def distances(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Distances (B, N) from ``x`` (B, N, D) to ``y[b, idx[b, n]]`` (idx (B, N) long), differentiable w.r.t.
        ``x`` and ``y``."""
        return torch.linalg.vector_norm(x - gather_points(self.y.to(x.dtype), idx), dim=-1)

    def reverse_query(self, x: torch.Tensor, order: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """For each point of ``y``: distances (B, M) to its nearest neighbour in ``x`` (B, N, D), differentiable
        w.r.t. ``x`` and ``y``, and its indices (B, M) into ``x``; ``nearest_neighbors(y, x)`` with ``y`` in
        ``x``'s dtype (``order``: see :meth:`indices`)."""
        idx = self.reverse_indices(x, order)
        return self.reverse_distances(x, idx), idx

    def reverse_distances(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Distances (B, M) from ``y`` to ``x[b, idx[b, m]]`` (x (B, N, D), idx (B, M) long), differentiable w.r.t.
        ``x`` and ``y``."""
        return torch.linalg.vector_norm(self.y.to(x.dtype) - gather_points(x, idx), dim=-1)


def nearest_neighbors(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    backend: Backend = "auto",
    block_elements: int | None = None,
    workers: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """For every point of ``x`` its nearest point of ``y`` (Euclidean), per batch element.

    Args:
        x: (B, N, D) float query points.
        y: (B, M, D) float reference points, same batch size, dtype family and device as ``x``.
        backend: ``"pykdtree"`` or ``"kdtree"`` (scipy) (k-d trees searched on the CPU), ``"torch"`` (blocked
            brute force on the tensors' device) or ``"auto"`` (:func:`default_backend`).
        block_elements: torch backend only, the largest number of pairwise distances held at once
            (default 2**22 on the CPU, 2**26 on CUDA, i.e. 16 MiB / 256 MiB in float32; twice that at the peak,
            with one coordinate's differences beside the sums).
        workers: ``"kdtree"`` backend only, threads used by the query (-1 for all cores).

    Returns:
        dists: (B, N) Euclidean distance to the nearest neighbour, differentiable w.r.t. ``x`` and ``y``.
        idx: (B, N) long index into ``y`` of the nearest neighbour.

    Raises:
        ValueError: on malformed shapes, empty clouds, mismatched batches or devices, or an unknown backend.

    Example:
        >>> x = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]])
        >>> y = torch.tensor([[[1.0, 1.0, 1.2], [0.0, 0.1, 0.0]]])
        >>> d, i = nearest_neighbors(x, y)
        >>> i.tolist(), [round(v, 3) for v in d[0].tolist()]
        ([[1, 0]], [0.1, 0.2])
    """
    check_points(x, "x", dim=None)
    check_points(y, "y", dim=None)
    check_same_batch(x, y, "x", "y")
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"x and y must have the same point dimension, got {x.shape[-1]} and {y.shape[-1]}")
    return NearestNeighborIndex(y, backend=backend, block_elements=block_elements, workers=workers).query(x)
