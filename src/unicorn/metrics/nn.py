"""Exact nearest-neighbour search between point clouds in bounded memory.

Two backends find the neighbour indices without gradient; the distances are then recomputed in torch from the
matched pairs, so they are exact (no ``|x|^2 - 2 x.y + |y|^2`` cancellation) and differentiable with respect
to both clouds.

- ``"kdtree"``: :class:`scipy.spatial.cKDTree` on the CPU (float64). On 2 CPU cores a 100k x 100k search takes
  about 0.15 s (build 0.05 s, query 0.1 s) against about 50 s for the brute-force torch search with one
  thread, so it is the default for CPU tensors.
- ``"torch"``: brute force in blocks of at most ``block_elements`` pairwise distances (a running minimum over
  blocks of ``y``), so memory stays bounded whatever the cloud sizes. It is the default for CUDA tensors,
  where a 100k x 100k search is a few tens of milliseconds and avoids a device round trip.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
from scipy.spatial import cKDTree

from unicorn.checks import check_points, check_same_batch

__all__ = ["Backend", "NearestNeighborIndex", "gather_points", "nearest_neighbors"]

Backend = Literal["auto", "kdtree", "torch"]


def gather_points(y: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Pick ``y[b, idx[b, n]]``: y (B, M, D), idx (B, N) long -> (B, N, D)."""
    return torch.gather(y, 1, idx.unsqueeze(-1).expand(-1, -1, y.shape[-1]))


def _torch_indices(x: torch.Tensor, y: torch.Tensor, block_elements: int) -> torch.Tensor:
    x, y = x.detach(), y.detach()
    B, N, _ = x.shape
    M = y.shape[1]
    cols = min(M, max(1, int(np.sqrt(block_elements))))
    rows = min(N, max(1, block_elements // cols))
    out = torch.empty(B, N, dtype=torch.long, device=x.device)
    for b in range(B):
        # centring on y's mean reduces the cancellation of the matrix-product form of cdist
        centre = y[b].mean(0, keepdim=True)
        xb, yb = x[b] - centre, y[b] - centre
        for r0 in range(0, N, rows):
            xs = xb[r0 : r0 + rows]
            best = torch.full((xs.shape[0],), float("inf"), dtype=x.dtype, device=x.device)
            best_idx = torch.zeros(xs.shape[0], dtype=torch.long, device=x.device)
            for c0 in range(0, M, cols):
                d, j = torch.cdist(xs, yb[c0 : c0 + cols]).min(dim=1)
                better = d < best
                best = torch.where(better, d, best)
                best_idx = torch.where(better, j + c0, best_idx)
            out[b, r0 : r0 + rows] = best_idx
    return out


class NearestNeighborIndex:
    """A reusable search structure over reference clouds ``y`` (B, M, D), for repeated queries.

    With the kdtree backend the trees are built once here, which is what an optimisation loop with a fixed
    target (ICP) wants.

    Args:
        y: (B, M, D) float reference points.
        backend: ``"kdtree"``, ``"torch"`` or ``"auto"``, see :func:`nearest_neighbors`.
        block_elements: torch backend only, the largest number of pairwise distances held at once.
        workers: kdtree backend only, query threads (-1 for all cores).
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
            backend = "torch" if y.device.type == "cuda" else "kdtree"
        if backend not in ("kdtree", "torch"):
            raise ValueError(f"backend must be 'auto', 'kdtree' or 'torch', got {backend!r}")
        if block_elements is None:
            block_elements = 2**26 if y.device.type == "cuda" else 2**22
        if block_elements < 1:
            raise ValueError(f"block_elements must be positive, got {block_elements}")
        self.y = y
        self.backend = backend
        self.block_elements = int(block_elements)
        self.workers = workers
        self._trees = None
        if backend == "kdtree":
            # sliding-midpoint trees with larger leaves: 3-4x faster than scipy's defaults for queries far
            # from a surface sample (the first ICP iterations), as fast otherwise
            self._trees = [
                cKDTree(
                    yb.detach().to(device="cpu", dtype=torch.float64).numpy(),
                    leafsize=32,
                    balanced_tree=False,
                    compact_nodes=False,
                )
                for yb in y
            ]

    @torch.no_grad()
    def indices(self, x: torch.Tensor) -> torch.Tensor:
        """Indices (B, N) long into ``y`` of the nearest neighbours of ``x`` (B, N, D), without gradient."""
        check_points(x, "x", dim=None)
        check_same_batch(x, self.y, "x", "y")
        if x.shape[-1] != self.y.shape[-1]:
            raise ValueError(f"x and y must have the same point dimension, got {x.shape[-1]} and {self.y.shape[-1]}")
        if self._trees is not None:
            out = []
            for xb, tree in zip(x.detach(), self._trees):
                _, idx = tree.query(xb.to(device="cpu", dtype=torch.float64).numpy(), k=1, workers=self.workers)
                out.append(torch.from_numpy(np.asarray(idx, dtype=np.int64)))
            return torch.stack(out).to(x.device)
        return _torch_indices(x, self.y.to(x.dtype), self.block_elements)

    def query(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances (B, N), differentiable w.r.t. ``x`` and ``y``, and indices (B, N) of the neighbours."""
        idx = self.indices(x)
        dists = torch.linalg.vector_norm(x - gather_points(self.y.to(x.dtype), idx), dim=-1)
        return dists, idx


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
        backend: ``"kdtree"`` (scipy, CPU), ``"torch"`` (blocked brute force, any device) or ``"auto"``
            (torch on CUDA, kdtree otherwise).
        block_elements: torch backend only, the largest number of pairwise distances held at once
            (default 2**22 on the CPU, 2**26 on CUDA, i.e. 16 MiB / 256 MiB in float32).
        workers: kdtree backend only, threads used by the query (-1 for all cores).

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
