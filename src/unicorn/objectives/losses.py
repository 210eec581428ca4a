"""Reconstruction, mesh and pose losses.

Per-sample terms keep a (B,) (or (K*B,)) shape until the probability weighting; mesh regularisers are batch
scalars unless asked per mesh (``reduction="none"``), the pose prior is a batch scalar.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from unicorn.checks import check_shape
from unicorn.geometry.rotations import rotation_angle_between
from unicorn.model.pose import PoseHead, PoseOutput, mirrored_pose
from unicorn.objectives.perceptual import build_perceptual

__all__ = [
    "MeshRegularizer",
    "NormalConsistencyLoss",
    "ReconstructionLoss",
    "UniformLaplacianLoss",
    "candidate_assignment_loss",
    "candidate_spacing_loss",
    "flip_consistency_loss",
    "mse_per_sample",
    "uniform_pose_prior",
    "view_equivariance_loss",
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
    check_shape(probs, "K, B", "probs")
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
    dims = check_shape(log_probs, "K, B", "log_probs")
    check_shape(losses, "K, B", "losses", dims)
    best = losses.detach().argmin(0)  # (B,)
    return -log_probs.gather(0, best.unsqueeze(0)).mean()


def candidate_spacing_loss(R: torch.Tensor, min_angle: float) -> torch.Tensor:
    """How close each image's pose candidates are to one another: ``mean_b sum_{k<l} relu(1 - d[k, l, b] /
    min_angle)``, ``d`` the geodesic angle between candidates k and l in degrees.

    Each pair of candidates nearer than ``min_angle`` adds up to 1; pairs further apart add nothing. The gradient
    pushes near candidates apart (e.g. two neighbours on the azimuth their sectors share), at ``1 / min_angle`` per
    degree; two exactly equal rotations add 1 without a push (the angle's gradient is 0 there).

    Args:
        R: (K, B, 3, 3) candidate rotations.
        min_angle: the angle in degrees (> 0) from which a pair adds nothing.

    Returns:
        scalar.
    """
    K = check_shape(R, "K, B, 3, 3", "R")["K"]
    if min_angle <= 0:
        raise ValueError(f"min_angle must be > 0, got {min_angle}")
    k, l = torch.triu_indices(K, K, offset=1, device=R.device)
    angles = rotation_angle_between(R[k], R[l])  # (pairs, B)
    return torch.relu(1 - angles / min_angle).sum(0).mean()


def flip_consistency_loss(poses: PoseOutput, flipped: PoseOutput, mirror: torch.Tensor) -> torch.Tensor:
    """How far the pose candidates of horizontally flipped images are from the mirrors of the images' own:
    candidate ``mirror[k]`` of a flipped image should be candidate k's :func:`~unicorn.model.pose.mirrored_pose`,
    with its probability. A model that sees two mirror views (a car from its left and from its right) as one view
    pays it; a category symmetric through the plane z = 0 of its canonical frame pays nothing.

    ``mean_{k,b} (|R_f[m_k] - R'_k|^2_F + |T_f[m_k] - T'_k|^2) + mean_b KL(p || p_f[m]) + mean_b KL(p_f[m] || p)``,
    each KL with its first argument detached, so that both predictions move toward each other.

    Args:
        poses: the images' K candidates (R (K, B, 3, 3), T (K, B, 3), log_probs (K, B)).
        flipped: the flipped images' candidates, of the same shapes.
        mirror: (K,) long, :meth:`unicorn.model.pose.PoseHead.mirror_index`.

    Returns:
        scalar.
    """
    K = check_shape(poses.R, "K, B, 3, 3", "poses.R")["K"]
    check_shape(mirror, "K", "mirror", {"K": K})
    R_target, T_target = mirrored_pose(poses.R, poses.T)
    R_f, T_f, lp_f = flipped.R[mirror], flipped.T[mirror], flipped.log_probs[mirror]
    geometry = (R_f - R_target).square().sum((-2, -1)).mean() + (T_f - T_target).square().sum(-1).mean()
    lp = poses.log_probs
    kl = (lp.exp().detach() * (lp.detach() - lp_f)).sum(0).mean()
    kl = kl + (lp_f.exp().detach() * (lp_f.detach() - lp)).sum(0).mean()
    return geometry + kl


def view_equivariance_loss(
    poses: PoseOutput,
    moved: PoseOutput,
    roll: torch.Tensor,
    shift: torch.Tensor,
    head: PoseHead,
    focal_length: float | torch.Tensor,
) -> torch.Tensor:
    """How far the pose candidates of rolled and shifted images (:func:`unicorn.data.augment.roll_shift_images`)
    are from the images' own candidates rolled and shifted alike: the same azimuth, elevation and probabilities,
    the roll plus the image's, the translation turned with the image and moved by ``shift * T_z / f``.

    Turning an image about its centre is rolling the camera about its optical axis (the last factor of
    :func:`~unicorn.geometry.rotations.azim_elev_roll_to_rotation`), so the viewpoint's azimuth and elevation must
    not follow it; this is the term's point: a pose branch that reads the azimuth from where the object sits or
    how it leans pays it. The targets (the images' own candidates) are detached; each angle and translation error
    is measured in units of its offset range, the targets clamped into the head's reach. Angles and translation
    axes without range, angles the head holds (``use_elevation_roll``) and a held translation (``use_translation``)
    leave their terms out.

    ``mean_{k,b} sum_i ((a'_i - a*_i) / range_i)^2 + mean_{k,b} sum_j ((T'_j - T*_j) / T_range_j)^2
    + mean_b KL(p || p')``.

    Args:
        poses: the images' K candidates (angles (K, B, 3), T (K, B, 3), log_probs (K, B)).
        moved: the rolled and shifted images' candidates, of the same shapes.
        roll: (B,) the images' roll, degrees; shift: (B, 2) their shift, NDC.
        head: the pose head both came from (its ranges and holds).
        focal_length: the camera's, in NDC units.

    Returns:
        scalar.
    """
    dims = check_shape(poses.angles, "K, B, 3", "poses.angles")
    K, B = dims["K"], dims["B"]
    check_shape(moved.angles, "K, B, 3", "moved.angles", {"K": K, "B": B})
    check_shape(roll, "B", "roll", {"B": B})
    check_shape(shift, "B, 2", "shift", {"B": B})
    angles = poses.angles.detach()
    target = torch.cat([angles[..., :2], angles[..., 2:] + roll.to(angles).view(1, B, 1)], -1)
    anchors, reach = head.R_init.unsqueeze(1), head.R_range
    target = torch.minimum(torch.maximum(target, anchors - reach), anchors + reach)
    tilt = head.use_elevation_roll.to(angles.dtype)
    # an angle without range (a fixed elevation) or held at its anchor has nothing to learn; the azimuth is never held
    used = torch.stack([torch.ones_like(tilt), tilt, tilt]) * (reach > 0).to(angles.dtype)
    loss = (((moved.angles - target) / torch.where(reach > 0, reach, 1.0)).square() * used).sum(-1).mean()
    T = poses.T.detach()
    r = torch.deg2rad(roll.to(T)).view(1, B)
    c, s = r.cos(), r.sin()
    depth = T[..., 2] / focal_length  # (K, B): an NDC shift moves the object this much in view units
    x = c * T[..., 0] - s * T[..., 1] + shift[:, 0].to(T).view(1, B) * depth
    y = s * T[..., 0] + c * T[..., 1] + shift[:, 1].to(T).view(1, B) * depth
    T_target = torch.stack([x, y, T[..., 2]], -1)
    T_target = torch.minimum(torch.maximum(T_target, head.T_init - head.T_range), head.T_init + head.T_range)
    # a held translation, or an axis without range, has nothing to learn
    free = (head.T_range > 0).to(T.dtype) * head.use_translation.to(T.dtype)
    t_err = ((moved.T - T_target) / torch.where(head.T_range > 0, head.T_range, 1.0)).square() * free
    kl = (poses.log_probs.detach().exp() * (poses.log_probs.detach() - moved.log_probs)).sum(0).mean()
    return loss + t_err.sum(-1).mean() + kl


def _edges_and_opposites(faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unique edges (E, 2) of a closed manifold mesh and the vertices opposite each in its 2 faces (E, 2)."""
    check_shape(faces, "F, 3", "faces")
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
        check_shape(verts, "B, V, 3", "verts")
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
        check_shape(faces, "F, 3", "faces")
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
        check_shape(verts, "B, V, 3", "verts", {"V": self.neighbors.shape[0]})
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


class ReconstructionLoss(nn.Module):
    """Weighted per-sample reconstruction terms ``{"rgb": (N,), "perceptual": (N,)}`` of renders against targets.

    Like the reference, a term whose weight is <= 0 is left out entirely (and so is the perceptual term without a
    perceptual loss).

    Args:
        rgb_weight: weight of the pixel MSE (:func:`mse_per_sample`).
        perceptual: a per-sample perceptual loss ``(N, 3, H, W) x 2 -> (N,)``, or None.
        perceptual_weight: its weight.
    """

    def __init__(self, rgb_weight: float = 1.0, perceptual: nn.Module | None = None, perceptual_weight: float = 0.0):
        super().__init__()
        self.rgb_weight, self.perceptual_weight = rgb_weight, perceptual_weight
        self.perceptual = perceptual

    @classmethod
    def from_config(cls, loss: Mapping[str, Any]) -> ReconstructionLoss:
        """From a model configuration's ``loss`` group (the perceptual loss built by name,
        :func:`unicorn.objectives.perceptual.build_perceptual`)."""
        perceptual = build_perceptual(loss["perceptual"], **loss)
        return cls(loss["rgb_weight"], perceptual, loss["perceptual_weight"])

    def forward(self, rec: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
        """(N, 3, H, W) renders and targets -> the weighted terms, each (N,)."""
        terms = {}
        if self.rgb_weight > 0:
            terms["rgb"] = self.rgb_weight * mse_per_sample(rec, target)
        if self.perceptual is not None and self.perceptual_weight > 0:
            terms["perceptual"] = self.perceptual_weight * self.perceptual(rec, target)
        return terms


class MeshRegularizer(nn.Module):
    """Weighted mesh regularisers ``{"normal": ..., "laplacian": ...}`` of meshes sharing the template's faces.

    A term whose weight is <= 0 is left out.

    Args:
        faces: (F, 3) faces of a closed manifold mesh; num_verts: V.
        normal_weight: weight of :class:`NormalConsistencyLoss`; laplacian_weight: of :class:`UniformLaplacianLoss`.
    """

    def __init__(self, faces: torch.Tensor, num_verts: int, normal_weight: float, laplacian_weight: float) -> None:
        super().__init__()
        self.normal_weight, self.laplacian_weight = normal_weight, laplacian_weight
        self.normal = NormalConsistencyLoss(faces)
        self.laplacian = UniformLaplacianLoss(faces, num_verts)

    @classmethod
    def from_config(cls, loss: Mapping[str, Any], faces: torch.Tensor, num_verts: int) -> MeshRegularizer:
        """From a model configuration's ``loss`` group and the template's faces (F, 3) and vertex count."""
        return cls(faces, num_verts, loss["normal_weight"], loss["laplacian_weight"])

    def forward(self, verts: torch.Tensor, reduction: str = "mean") -> dict[str, torch.Tensor]:
        """(B, V, 3) -> weighted scalars (``reduction="mean"``) or (B,) per mesh (``"none"``)."""
        terms = {}
        if self.normal_weight > 0:
            terms["normal"] = self.normal_weight * self.normal(verts, reduction=reduction)
        if self.laplacian_weight > 0:
            terms["laplacian"] = self.laplacian_weight * self.laplacian(verts, reduction=reduction)
        return terms
