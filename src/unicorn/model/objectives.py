"""The training objectives of :class:`~unicorn.model.Unicorn`: the pose step, the 3D step, the neighbour loss.

Each step takes a model and a batch of images and returns its weighted loss terms together with the batch's
pose-candidate probabilities (:class:`StepLosses`), which is all a trainer needs (``unicorn.lit`` logs the
candidate shares from them). Each step detaches what the paper says, so only its own branches receive gradients.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from unicorn.model.generator import mean_texture
from unicorn.model.losses import candidate_assignment_loss, mse_per_sample, uniform_pose_prior

if TYPE_CHECKING:
    from unicorn.model.autoencoder import Unicorn

__all__ = ["StepLosses", "neighbor_loss", "pose_step", "reconstruction_terms", "step_3d"]


class StepLosses(dict):
    """A step's weighted loss terms (name -> scalar tensor, summing to ``"total"``) and ``probs``, the batch's
    pose-candidate probabilities (K, B), detached."""

    def __init__(self, terms: dict[str, torch.Tensor], probs: torch.Tensor) -> None:
        super().__init__(terms)
        self.probs = probs


def reconstruction_terms(model: Unicorn, rec: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    """Weighted per-sample terms ``{"rgb": (N,), "perceptual": (N,)}`` (perceptual only if enabled)."""
    ls = model.config["loss"]
    terms = {}
    # like the reference, a weight <= 0 drops the term entirely
    if ls["rgb_weight"] > 0:
        terms["rgb"] = ls["rgb_weight"] * mse_per_sample(rec, target)
    if model.perceptual is not None and ls["perceptual_weight"] > 0:
        terms["perceptual"] = ls["perceptual_weight"] * model.perceptual(rec, target)
    return terms


def pose_step(model: Unicorn, images: torch.Tensor, average_texture: bool = False) -> StepLosses:
    """P-step: all K candidates rendered with detached shapes, textures and backgrounds.

    ``total = mean_b sum_k p[k, b] * L_rec(k, b) + uniform_weight * L_uni``; gradients reach the pose
    branch (rotation, translation and probability heads, and the encoder that feeds them) only. With
    ``loss.pose_objective = "assigned"`` the weights ``p`` are detached and the probabilities learn from
    ``assignment_weight * candidate_assignment_loss`` instead (term ``assignment``).

    Args:
        images: (B, 3, S, S) in [0, 1].
        average_texture: replace every texture by its mean colour (drawn once per batch by the trainer).

    Returns:
        scalars ``total``, ``rgb``, ``perceptual`` (if enabled), ``uniform``; each already weighted,
        and the reconstruction terms probability-weighted like the total, so that they sum to ``total``;
        ``.probs``: the candidate probabilities (K, B), detached.
    """
    model.check_images(images)
    branches = model.branches()
    shared = len(model.encoders) == 1
    feats = model.encode(images, ("pose",) if not shared else branches)
    with torch.no_grad():
        # detached 3D branches: computing them without autograd is the same and cheaper
        other = feats if shared else model.encode(images, tuple(b for b in branches if b != "pose"))
        other = {k: v.detach() for k, v in other.items()}
        _, canonical, scale, _, maps, _, bkg = model.predict_3d(other, average_texture)
        verts = canonical * scale.unsqueeze(1)
    poses = model.pose(feats["pose"])
    K, B = poses.probs.shape
    R, T = poses.flat()
    rec, _ = model.render(
        verts.repeat(K, 1, 1),
        maps.repeat(K, 1, 1, 1),
        R,
        T,
        None if bkg is None else bkg.repeat(K, 1, 1, 1),
    )
    terms = reconstruction_terms(model, rec, images.repeat(K, 1, 1, 1))
    ls = model.config["loss"]
    assigned = ls["pose_objective"] == "assigned"
    weights = poses.probs.detach() if assigned else poses.probs
    out = {name: (weights * value.view(K, B)).sum(0).mean() for name, value in terms.items()}
    if assigned and terms:
        per_candidate = torch.stack(list(terms.values())).sum(0).view(K, B)
        out["assignment"] = ls["assignment_weight"] * candidate_assignment_loss(poses.log_probs, per_candidate)
    if ls["uniform_weight"] > 0:
        out["uniform"] = ls["uniform_weight"] * uniform_pose_prior(poses.probs, ls["uniform_reduction"])
    out["total"] = torch.stack(list(out.values())).sum() if out else images.new_zeros(())
    return StepLosses(out, poses.probs.detach())


def step_3d(model: Unicorn, images: torch.Tensor, average_texture: bool = False) -> StepLosses:
    """3D-step: the most likely candidate rendered with a detached pose.

    ``total = mean_b [L_rec + w_nbr * L_nbr] + w_norm * L_norm + w_lap * L_lap`` (``*_weight`` keys);
    gradients reach the shape, scale, texture and background branches (and their encoders) only.
    The neighbour term is active once both the shape and texture codes have active dimensions.

    Args:
        images: (B, 3, S, S) in [0, 1].
        average_texture: replace every texture by its mean colour (drawn once per batch by the trainer).

    Returns:
        weighted scalars ``total``, ``rgb``, ``perceptual`` (if enabled), ``normal``, ``laplacian`` and
        ``neighbor`` (when active); they sum to ``total``; ``.probs``: the candidate probabilities (K, B) of the
        pose prediction the step rendered with (computed without gradient).
    """
    model.check_images(images)
    branches = model.branches()
    shared = len(model.encoders) == 1
    feats = model.encode(images, branches if shared else tuple(b for b in branches if b != "pose"))
    with torch.no_grad():
        pose_feats = feats["pose"] if shared else model.encode(images, ("pose",))["pose"]
        poses = model.pose(pose_feats.detach())
        R, T = poses.select()
    z_sh, canonical, scale, z_tx, maps, _, bkg = model.predict_3d(feats, average_texture)
    verts = canonical * scale.unsqueeze(1)
    rec, _ = model.render(verts, maps, R, T, bkg)
    per_sample = reconstruction_terms(model, rec, images)
    ls = model.config["loss"]
    use_nbr = ls["neighbor_weight"] > 0 and model.shape.mask.active_dims > 0 and model.texture.mask.active_dims > 0
    if use_nbr:
        per_sample["neighbor"] = ls["neighbor_weight"] * neighbor_loss(
            model, images, z_sh, z_tx, canonical, maps, R, average_texture
        )
    out = {name: value.mean() for name, value in per_sample.items()}
    if ls["normal_weight"] > 0:
        out["normal"] = ls["normal_weight"] * model.normal_loss(verts)
    if ls["laplacian_weight"] > 0:
        out["laplacian"] = ls["laplacian_weight"] * model.laplacian_loss(verts)
    out["total"] = torch.stack(list(out.values())).sum() if out else images.new_zeros(())
    return StepLosses(out, poses.probs)


def neighbor_loss(
    model: Unicorn,
    images: torch.Tensor,
    shape_code: torch.Tensor,
    texture_code: torch.Tensor,
    canonical_verts: torch.Tensor,
    maps: torch.Tensor,
    R: torch.Tensor,
    average_texture: bool = False,
) -> torch.Tensor:
    """Neighbour reconstruction (unweighted), per sample (B,); 0 for samples without a neighbour.

    The batch is pushed to the memory first. For each sample a viewpoint bin is drawn and the nearest
    shape and texture neighbours in it are found; their parameters are recomputed with the current
    network without gradient. Swap 1 renders this sample's shape (with gradient) with the shape
    neighbour's scale, texture, pose and background; swap 2 renders the texture neighbour's mesh with
    this sample's texture (with gradient). Each is compared with the neighbour's image.

    Args:
        images: (B, 3, S, S); shape_code: (B, Cs); texture_code: (B, Ct) masked codes;
        canonical_verts: (B, V, 3) deformed templates; maps: (B, 3, Ht, Wt) textures; R: (B, 3, 3)
        hard-selected rotations.
    """
    B = images.shape[0]
    self_index = model.memory.push(images, shape_code, texture_code, R)
    match = model.memory.search(shape_code.detach(), texture_code.detach(), R, self_index)
    loss = images.new_zeros(B)
    # a host sync: the swaps run on the samples that found neighbours only (all of them once the memory
    # holds a few batches); padding the others would change the neighbour batch's BatchNorm statistics
    idx = match.valid.nonzero().squeeze(1)
    if idx.numel() == 0:
        return loss
    nbr_images = torch.cat([model.memory.images[match.shape_index[idx]], model.memory.images[match.texture_index[idx]]])
    n = idx.numel()
    with torch.no_grad():
        nbr_scale, nbr_maps, nbr_verts, nbr_R, nbr_T, nbr_bkg = _neighbour_parameters(
            model, nbr_images, n, average_texture
        )
    verts = torch.cat([canonical_verts[idx] * nbr_scale.unsqueeze(1), nbr_verts])
    tex = torch.cat([nbr_maps, maps[idx]])
    rec, _ = model.render(verts, tex, nbr_R, nbr_T, nbr_bkg)
    terms = reconstruction_terms(model, rec, nbr_images)
    if not terms:
        return loss
    per = sum(terms.values())
    return loss.index_put((idx,), per[:n] + per[n:])


def _neighbour_parameters(
    model: Unicorn, images: torch.Tensor, n: int, average_texture: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """What the two swaps take from the neighbours (call without gradient).

    ``images`` (2n, 3, S, S) holds the n shape neighbours then the n texture neighbours. The encoders see
    all 2n images together (their batch statistics are those of :meth:`predict` on the same batch); the
    heads compute only what a swap uses: the shape neighbours' scales (n, 3) and texture maps
    (n, 3, Ht, Wt), the texture neighbours' world vertices (n, V, 3), and everyone's R (2n, 3, 3),
    T (2n, 3) and background (2n, 3, S, S) or None.
    """
    feats = model.encode(images, model.branches())
    scale = model.scale(feats["shape"])
    z_sh = model.shape.code(feats["shape"][n:])
    verts = (model.template.verts + model.shape(model.template.verts, z_sh)) * scale[n:].unsqueeze(1)
    maps = model.texture(model.texture.code(feats["texture"][:n]))
    if average_texture:
        maps = mean_texture(maps)
    bkg = None
    if model.background is not None:
        bkg = model.background(model.background.code(feats["background"]))
    R, T = model.pose(feats["pose"]).select()
    return scale[:n], maps, verts, R, T, bkg
