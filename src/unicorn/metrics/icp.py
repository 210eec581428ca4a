"""Gradient-based ICP with rotation, translation and (anisotropic) scale, as UNICORN's evaluation runs it.

The source cloud ``P`` is moved by ``p' = (s * p) @ R + T`` with ``R`` from a 6D representation (Zhou et al.
2019, Gram-Schmidt on two 3-vectors, initialised at the identity ``[1, 0, 0, 0, 1, 0]``), ``T`` (initialised
at 0) and a per-axis scale ``s`` (initialised at 1). Adam (learning rate 0.01) minimises the squared Chamfer
distance (mean squared NN distance in each direction, summed) for ``n_iter`` iterations, the nearest
neighbours being found again at every iteration (exactly, by :class:`~unicorn.metrics.moving.MovingQueries`
from the previous iteration's answers). Keep-best rule: every ``window`` iterations the mean loss of the last
window is compared with the best window so far and, if lower, the parameters at that moment (after the window's
last step) become the result. The last, possibly partial, window is compared too.

Differences from the reference, on purpose:

- the keep-best rule is applied per object instead of on the batch-mean loss (with Adam, which is
  element-wise, objects of a batch are otherwise optimised independently, so a batch gives the same result as
  one-by-one runs);
- normals are transformed with the inverse transpose of the linear part, ``n' ~ (n / s) @ R`` renormalised, so
  that the normal consistency after ICP is meaningful (the reference left them unrotated).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from unicorn.checks import ShapeError, check_normals, check_points, check_same_batch, check_shape

from .moving import MovingQueries
from .nn import Backend, NearestNeighborIndex, spatial_order

__all__ = [
    "ICPResult",
    "apply_similarity",
    "gradient_icp",
    "matrix_to_rotation_6d",
    "rotation_6d_to_matrix",
    "transform_normals",
]


def rotation_6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from the 6D representation by Gram-Schmidt (Zhou et al., CVPR 2019).

    The two 3-vectors become the first two **rows** of the matrix (PyTorch3D's convention), so
    ``rotation_6d_to_matrix(matrix_to_rotation_6d(R)) == R``.

    Args:
        d6: (..., 6) two stacked 3-vectors, not parallel.

    Returns:
        (..., 3, 3) rotation matrices.

    Example:
        >>> rotation_6d_to_matrix(torch.tensor([2.0, 0.0, 0.0, 1.0, 3.0, 0.0])).tolist()
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    check_shape(d6, "*, 6", "d6")
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-2)


def matrix_to_rotation_6d(R: torch.Tensor) -> torch.Tensor:
    """The 6D representation (..., 6) of rotations (..., 3, 3): their first two rows."""
    check_shape(R, "*, 3, 3", "R")
    return R[..., :2, :].reshape(*R.shape[:-2], 6)


def apply_similarity(points: torch.Tensor, R: torch.Tensor, T: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``(scale * points) @ R + T``: points (B, N, 3), R (B, 3, 3), T (B, 3), scale (B, 3) -> (B, N, 3)."""
    return (points * scale.unsqueeze(1)) @ R + T.unsqueeze(1)


def transform_normals(normals: torch.Tensor, R: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Normals under ``p -> (scale * p) @ R + T``: ``normalize((normals / scale) @ R)``.

    Args:
        normals: (B, N, 3) normals.
        R: (B, 3, 3) rotations applied as ``x @ R``.
        scale: (B, 3) per-axis scales, non-zero.

    Returns:
        (B, N, 3) unit normals (zero where the input normal is zero).
    """
    return torch.nn.functional.normalize((normals / scale.unsqueeze(1)) @ R, dim=-1, eps=1e-12)


class ICPResult(NamedTuple):
    """Output of :func:`gradient_icp`.

    Attributes:
        points: (B, N, 3) the source points moved by the kept parameters.
        normals: (B, N, 3) the source normals transformed accordingly, None when none were given.
        R: (B, 3, 3) rotations, applied as ``x @ R``.
        T: (B, 3) translations.
        scale: (B, 3) per-axis scales (all equal when isotropic, ones when not estimated).
        loss: (B,) the mean squared-Chamfer loss of the window that selected the parameters.
    """

    points: torch.Tensor
    normals: torch.Tensor | None
    R: torch.Tensor
    T: torch.Tensor
    scale: torch.Tensor
    loss: torch.Tensor


def gradient_icp(
    src: torch.Tensor,
    tgt: torch.Tensor,
    src_normals: torch.Tensor | None = None,
    *,
    n_iter: int = 100,
    lr: float = 0.01,
    estimate_scale: bool = True,
    anisotropic_scale: bool = True,
    window: int = 10,
    backend: Backend = "auto",
    workers: int = 1,
    tgt_index: NearestNeighborIndex | None = None,
) -> ICPResult:
    """Align ``src`` onto ``tgt`` by Adam on the squared Chamfer distance over ``(R, T, s)``.

    Runs with gradients enabled even when called under :func:`torch.no_grad`; the inputs are not
    differentiated.

    Args:
        src: (B, N, 3) source points (the prediction, normalised to the unit cube in UNICORN's protocol).
        tgt: (B, M, 3) target points (the ground truth).
        src_normals: (B, N, 3) normals of ``src`` to carry along, optional.
        n_iter: Adam iterations (100 in UNICORN's final evaluation, 30 in its validation).
        lr: Adam learning rate.
        estimate_scale: optimise a scale; otherwise it stays 1 (rigid ICP).
        anisotropic_scale: one scale per axis (otherwise one per object); used when ``estimate_scale``.
        window: iterations per keep-best window.
        backend: nearest-neighbour backend, see :func:`unicorn.metrics.nn.nearest_neighbors`.
        workers: kdtree query threads.
        tgt_index: a :class:`~unicorn.metrics.nn.NearestNeighborIndex` over ``tgt`` (the same points) to reuse,
            e.g. across the ICPs of several predictions against one ground truth; ``backend`` and ``workers``
            are then its own. None: one is built here.

    Returns:
        :class:`ICPResult`.

    Raises:
        ValueError: on malformed inputs, non-positive ``n_iter``, ``window`` or ``lr``, or a ``tgt_index`` of
            another shape than ``tgt``.
    """
    _check_icp_args(src, tgt, src_normals, n_iter, lr, window, tgt_index)
    src, tgt = src.detach(), tgt.detach().to(src.dtype)
    B = src.shape[0]
    d6 = src.new_tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]).repeat(B, 1)
    T = src.new_zeros(B, 3)
    s = src.new_ones(B, 3 if anisotropic_scale else 1)
    params = [d6, T] + ([s] if estimate_scale else [])
    for p in params:
        p.requires_grad_(True)
    optimizer = torch.optim.Adam(params, lr=lr)
    if tgt_index is None:
        tgt_index = NearestNeighborIndex(tgt, backend=backend, workers=workers)
    # the source's Z-order stays a spatially coherent order of the moved points: computed once for all queries
    order = spatial_order(src)
    # the source moves by small steps: the nearest points change little from one step to the next
    searches = MovingQueries(tgt_index)
    best = _KeepBest((d6, T, s), window, n_iter)
    with torch.enable_grad():
        for it in range(n_iter):
            optimizer.zero_grad(set_to_none=True)
            moved = apply_similarity(src, rotation_6d_to_matrix(d6), T, s.expand(B, 3))
            loss = _squared_chamfer(moved, searches, order)
            loss.mean().backward()
            optimizer.step()
            best.update(it, loss.detach(), (d6, T, s))

    with torch.no_grad():
        d6, T, s = best.params
        R = rotation_6d_to_matrix(d6)
        scale = s.expand(B, 3).clone()
        points = apply_similarity(src, R, T, scale)
        normals = None if src_normals is None else transform_normals(src_normals.to(src), R, scale)
    return ICPResult(points, normals, R, T, scale, best.loss)


def _check_icp_args(
    src: torch.Tensor,
    tgt: torch.Tensor,
    src_normals: torch.Tensor | None,
    n_iter: int,
    lr: float,
    window: int,
    tgt_index: NearestNeighborIndex | None,
) -> None:
    check_points(src, "src")
    check_points(tgt, "tgt")
    check_same_batch(src, tgt, "src", "tgt")
    if tgt_index is not None and tgt_index.y.shape != tgt.shape:
        raise ShapeError(f"tgt_index must index tgt {tuple(tgt.shape)}, got one over {tuple(tgt_index.y.shape)}")
    check_normals(src_normals, src, "src_normals")
    if n_iter < 1 or window < 1:
        raise ValueError(f"n_iter and window must be positive, got n_iter={n_iter}, window={window}")
    if not lr > 0:
        raise ValueError(f"lr must be positive, got {lr}")


def _squared_chamfer(moved: torch.Tensor, searches: MovingQueries, order: torch.Tensor) -> torch.Tensor:
    """(B,) mean squared NN distance of ``moved`` (B, N, 3) to the target plus that of the target to ``moved``,
    differentiable w.r.t. ``moved``; ``order``: (B, N) visiting order of ``moved``'s points."""
    idx_src, idx_tgt = searches.both_indices(moved, order)
    d_src = searches.index.distances(moved, idx_src)
    d_tgt = searches.index.reverse_distances(moved, idx_tgt)
    return d_src.square().mean(dim=1) + d_tgt.square().mean(dim=1)


class _KeepBest:
    """The keep-best rule: every ``window`` iterations (and at the last one) the mean loss of the window is
    compared per object with the best so far; the parameters of a better window are copied."""

    def __init__(self, params: tuple[torch.Tensor, ...], window: int, n_iter: int) -> None:
        self.params = [p.detach().clone() for p in params]
        self.loss = params[0].new_full((params[0].shape[0],), float("inf"))
        self.window, self.n_iter = window, n_iter
        self._losses: list[torch.Tensor] = []

    def update(self, it: int, loss: torch.Tensor, params: tuple[torch.Tensor, ...]) -> None:
        """Record iteration ``it``'s (B,) loss; at a window's end keep ``params`` where the window is better."""
        self._losses.append(loss)
        if (it + 1) % self.window and it + 1 != self.n_iter:
            return
        mean = torch.stack(self._losses).mean(dim=0)
        self._losses = []
        better = mean < self.loss
        self.loss = torch.where(better, mean, self.loss)
        for kept, current in zip(self.params, params):
            kept.copy_(torch.where(better.view(-1, 1), current.detach(), kept))
