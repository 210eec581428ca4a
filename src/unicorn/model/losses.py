"""Reconstruction, mesh and pose losses.

Per-sample terms keep a (B,) (or (K*B,)) shape until the probability weighting; mesh regularisers are batch
scalars unless asked per mesh (``reduction="none"``), the pose prior is a batch scalar.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = [
    "NormalConsistencyLoss",
    "UniformLaplacianLoss",
    "candidate_assignment_loss",
    "mse_per_sample",
    "uniform_pose_prior",
]


def mse_per_sample(rec: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Squared error averaged over everything but the first dimension: (B, ...) x 2 -> (B,)."""
    if rec.shape != target.shape:
        raise ValueError(f"rec and target differ in shape: {tuple(rec.shape)} vs {tuple(target.shape)}")
    return (rec - target).pow(2).flatten(1).mean(1)


def uniform_pose_prior(probs: torch.Tensor, reduction: str = "sum") -> torch.Tensor:
    """Pose-candidate balance ``sum_k |mean_b p[k, b] - 1/K|`` (paper, eq. 3).

    Args:
        probs: (K, B) candidate probabilities.
        reduction: ``"sum"`` over candidates (paper) or ``"mean"`` (the reference code, i.e. the paper's
            value divided by K).

    Returns:
        scalar.
    """
    if probs.dim() != 2:
        raise ValueError(f"probs must have shape (K, B), got {tuple(probs.shape)}")
    dev = (probs.mean(1) - 1.0 / probs.shape[0]).abs()
    if reduction == "sum":
        return dev.sum()
    if reduction == "mean":
        return dev.mean()
    raise ValueError(f"reduction must be 'sum' or 'mean', got {reduction!r}")


def candidate_assignment_loss(log_probs: torch.Tensor, losses: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the candidate probabilities against the candidate that reconstructs best.

    ``mean_b -log p[k*(b), b]`` with ``k*(b) = argmin_k losses[k, b]``. Unlike the expected loss
    ``sum_k p[k, b] * losses[k, b]``, whose gradient on a candidate's logit is ``p[k, b] * (losses[k, b] - mean)``
    and vanishes once its probability is near 0, this moves the probability to whichever candidate reconstructs
    best, however unlikely it was: a pose assignment made early (e.g. a range of views predicted turned round
    while the shape was still symmetric) can be undone later.

    Args:
        log_probs: (K, B) log-probabilities of the candidates.
        losses: (K, B) reconstruction loss of each candidate (not differentiated).

    Returns:
        scalar.
    """
    if log_probs.dim() != 2 or log_probs.shape != losses.shape:
        raise ValueError(
            f"log_probs and losses must both have shape (K, B), got {tuple(log_probs.shape)} and {tuple(losses.shape)}"
        )
    best = losses.detach().argmin(0)  # (B,)
    return -log_probs.gather(0, best.unsqueeze(0)).mean()


def _edges_and_opposites(faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unique edges (E, 2) of a closed manifold mesh and the vertices opposite each in its 2 faces (E, 2)."""
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {tuple(faces.shape)}")
    faces = faces.long().cpu()
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    half = torch.cat([torch.stack([a, b], 1), torch.stack([b, c], 1), torch.stack([c, a], 1)])  # (3F, 2)
    opposite = torch.cat([c, a, b])
    key = half.sort(1).values
    n = int(faces.max()) + 1
    order = torch.argsort(key[:, 0] * n + key[:, 1])
    key, opposite = key[order], opposite[order]
    if key.shape[0] % 2 or not torch.equal(key[0::2], key[1::2]):
        raise ValueError("normal consistency needs a closed manifold mesh (every edge shared by exactly 2 faces)")
    edges = key[0::2]
    if edges.shape[0] > 1 and (edges[1:] == edges[:-1]).all(1).any():
        raise ValueError("normal consistency needs a closed manifold mesh (an edge is shared by more than 2 faces)")
    return edges, torch.stack([opposite[0::2], opposite[1::2]], 1)


class NormalConsistencyLoss(nn.Module):
    """Mean over edges (and batch) of ``1 - cos(n0, -n1)``, for the two faces sharing each edge.

    With edge (v0, v1) and opposite vertices a, b: ``n0 = (v1 - v0) x (a - v0)`` and
    ``n1 = (v1 - v0) x (b - v0)``;
    a flat neighbourhood gives 0, a fold 2. Equivalent to PyTorch3D's ``mesh_normal_consistency`` on a closed
    manifold. Topology is precomputed once from the shared faces.

    Args:
        faces: (F, 3) faces of a closed manifold mesh.
    """

    edges: torch.Tensor
    opposite: torch.Tensor

    def __init__(self, faces: torch.Tensor) -> None:
        super().__init__()
        edges, opposite = _edges_and_opposites(faces)
        self.register_buffer("edges", edges, persistent=False)
        self.register_buffer("opposite", opposite, persistent=False)

    def forward(self, verts: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
        """(B, V, 3) -> scalar (``reduction="mean"``), or (B,) per mesh (``"none"``)."""
        if verts.dim() != 3 or verts.shape[-1] != 3:
            raise ValueError(f"verts must have shape (B, V, 3), got {tuple(verts.shape)}")
        v0, v1 = verts[:, self.edges[:, 0]], verts[:, self.edges[:, 1]]
        e = v1 - v0
        n0 = torch.cross(e, verts[:, self.opposite[:, 0]] - v0, dim=-1)
        n1 = torch.cross(e, verts[:, self.opposite[:, 1]] - v0, dim=-1)
        cos = torch.nn.functional.cosine_similarity(n0, -n1, dim=-1, eps=1e-6)
        return _reduce((1 - cos).mean(1), reduction)


class UniformLaplacianLoss(nn.Module):
    """Uniform Laplacian smoothing: mean over vertices (and batch) of ``|| mean_{j in N(i)} v_j - v_i ||_2``.

    The L2 norm is not squared (PyTorch3D's ``mesh_laplacian_smoothing(method="uniform")``). Neighbour lists
    are precomputed as a padded (V, D) index with a validity mask.

    Args:
        faces: (F, 3) faces.
        num_verts: V (defaults to ``faces.max() + 1``).
    """

    neighbors: torch.Tensor
    weights: torch.Tensor

    def __init__(self, faces: torch.Tensor, num_verts: int | None = None) -> None:
        super().__init__()
        if faces.dim() != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got {tuple(faces.shape)}")
        faces = faces.long().cpu()
        V = int(faces.max()) + 1 if num_verts is None else int(num_verts)
        pairs = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        pairs = torch.unique(torch.cat([pairs, pairs.flip(1)]).sort(1).values, dim=0)  # undirected edges
        directed = torch.cat([pairs, pairs.flip(1)])
        directed = directed[torch.argsort(directed[:, 0] * V + directed[:, 1])]
        deg = torch.bincount(directed[:, 0], minlength=V)
        D = int(deg.max())
        start = torch.cumsum(deg, 0) - deg
        slot = torch.arange(directed.shape[0]) - start[directed[:, 0]]
        neighbors = torch.zeros(V, D, dtype=torch.long)
        weights = torch.zeros(V, D)
        neighbors[directed[:, 0], slot] = directed[:, 1]
        weights[directed[:, 0], slot] = 1.0 / deg[directed[:, 0]].float()
        self.register_buffer("neighbors", neighbors, persistent=False)
        self.register_buffer("weights", weights, persistent=False)

    def forward(self, verts: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
        """(B, V, 3) -> scalar (``reduction="mean"``), or (B,) per mesh (``"none"``)."""
        if verts.dim() != 3 or verts.shape[1:] != (self.neighbors.shape[0], 3):
            raise ValueError(f"verts must have shape (B, {self.neighbors.shape[0]}, 3), got {tuple(verts.shape)}")
        mean_nbr = (verts[:, self.neighbors] * self.weights.to(verts.dtype)[None, :, :, None]).sum(2)
        return _reduce((mean_nbr - verts).norm(dim=-1).mean(1), reduction)


def _reduce(per_mesh: torch.Tensor, reduction: str) -> torch.Tensor:
    """(B,) per-mesh values -> their mean (every mesh has the same edges and vertices: the mean over all) or
    themselves."""
    if reduction == "mean":
        return per_mesh.mean()
    if reduction == "none":
        return per_mesh
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
