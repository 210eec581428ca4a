"""UNICORN's structured autoencoder: image -> (shape, texture, pose, background) -> rendered image.

The model is a plain ``nn.Module``. A trainer calls :meth:`Unicorn.pose_step` and :meth:`Unicorn.step_3d`
on alternate iterations (one optimizer over all parameters is enough: each step detaches what the paper
says, so only its own branches receive gradients), and drives the progressive code sizes and stage-1
switches with :meth:`Unicorn.set_active_dims` and :meth:`Unicorn.set_stage_switches`.

Configuration (keyword groups, each a mapping merged over :data:`DEFAULT_CONFIG`; unknown keys raise):

- ``image_size``: input / render side (64).
- ``encoder``: ``shared`` (True: one ResNet-18; False: four, for shape, texture, pose and background).
- ``template``: ``level`` (3), ``axes`` ((1, 0.7, 0.7)), ``scale`` (0.6 real images, 0.4 ShapeNet),
  ``uv_mode`` ("seamless" or "reference", see :mod:`unicorn.model.template`).
- ``shape``: ``code_dim`` (32 small / 64 big), ``active_dims`` (0), ``n_field_units`` (128 / 512 ShapeNet),
  ``n_field_layers`` (2), ``n_reg_units`` (128), ``n_reg_layers`` (3).
- ``texture``: ``code_dim`` (128 / 512), ``active_dims`` (2), ``size`` (64), ``min_features`` (16 / 64),
  ``n_reg_units``, ``n_reg_layers``.
- ``background``: same keys as texture without ``size`` (code 128 / 256, active 4), or None for no
  background model (ShapeNet: objects over the renderer's white).
- ``pose``: ``n_elev`` (1), ``n_azim`` (6), ``azim_range`` ((0, 360)), ``elev_range`` ((-10, 30)),
  ``roll_range`` ((-30, 30)), ``T_range`` (0.3), ``prior_translation`` ((0, 0, 2.732)), ``scale_range``
  (0.3), ``n_units`` (128), ``n_layers`` (3).
- ``renderer``: ``name`` ("layered"), ``fov`` (30) or ``focal_length``, ``background_color`` ((1, 1, 1)),
  ``composite`` ("direct": the background image is the renderer's background; "reference": render over
  the white background colour, then ``rgb * A + (1 - A) * bkg`` as the released models did), ``options``
  (extra keyword arguments of :func:`unicorn.render.build_renderer`; {sigma: 1e-4, faces_per_pixel: 25}).
- ``loss``: ``rgb_weight`` (1), ``perceptual`` ("vgg", "structural" or None), ``perceptual_weight`` (10),
  ``vgg_weights`` (a copy of ``vgg16-397923af.pth``; None: torch's hub cache, downloaded), ``normal_weight``
  (0.01), ``laplacian_weight`` (0.01), ``uniform_weight`` (0.02), ``uniform_reduction`` ("sum" as in the
  paper, "mean" as in the reference code), ``pose_objective`` ("expected": the paper's probability-weighted
  loss trains the probabilities; "assigned": the reconstruction terms are weighted by the detached probabilities
  and the probabilities learn from ``assignment_weight`` (0.02) x the cross-entropy against the best-reconstructing
  candidate, see :func:`~unicorn.model.losses.candidate_assignment_loss`), ``neighbor_weight`` (1),
  ``memory_size`` (1024), ``n_bins`` (5), ``min_angle`` (20).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.model.encoder import ResNet18
from unicorn.model.field import ShapeHead
from unicorn.model.generator import CodeGenerator
from unicorn.model.losses import (
    POSE_OBJECTIVES,
    NormalConsistencyLoss,
    UniformLaplacianLoss,
    candidate_assignment_loss,
    mse_per_sample,
    uniform_pose_prior,
)
from unicorn.model.neighbors import NeighborMemory
from unicorn.model.perceptual import StructuralLoss, VGGPerceptualLoss
from unicorn.model.pose import PoseHead, PoseOutput, ScaleHead
from unicorn.model.template import TemplateMesh
from unicorn.render import TexturesUV, build_renderer

__all__ = ["DEFAULT_CONFIG", "BRANCHES", "Prediction", "Unicorn", "merge_config", "unicorn_config"]

BRANCHES = ("shape", "texture", "pose", "background")

DEFAULT_CONFIG: dict[str, Any] = {
    "image_size": 64,
    "encoder": {"shared": True},
    "template": {"level": 3, "axes": (1.0, 0.7, 0.7), "scale": 0.6, "uv_mode": "seamless"},
    "shape": {
        "code_dim": 32,
        "active_dims": 0,
        "n_field_units": 128,
        "n_field_layers": 2,
        "n_reg_units": 128,
        "n_reg_layers": 3,
    },
    "texture": {
        "code_dim": 128,
        "active_dims": 2,
        "size": 64,
        "min_features": 16,
        "n_reg_units": 128,
        "n_reg_layers": 3,
    },
    "background": {
        "code_dim": 128,
        "active_dims": 4,
        "min_features": 16,
        "n_reg_units": 128,
        "n_reg_layers": 3,
    },
    "pose": {
        "n_elev": 1,
        "n_azim": 6,
        "azim_range": (0.0, 360.0),
        "elev_range": (-10.0, 30.0),
        "roll_range": (-30.0, 30.0),
        "T_range": 0.3,
        "prior_translation": (0.0, 0.0, 2.732),
        "scale_range": 0.3,
        "n_units": 128,
        "n_layers": 3,
    },
    "renderer": {
        "name": "layered",
        "fov": 30.0,
        "focal_length": None,
        "background_color": (1.0, 1.0, 1.0),
        "composite": "direct",
        "options": {"sigma": 1e-4, "faces_per_pixel": 25},
    },
    "loss": {
        "rgb_weight": 1.0,
        "perceptual": "vgg",
        "perceptual_weight": 10.0,
        "vgg_weights": None,
        "normal_weight": 0.01,
        "laplacian_weight": 0.01,
        "uniform_weight": 0.02,
        "uniform_reduction": "sum",
        "pose_objective": "expected",
        "assignment_weight": 0.02,
        "neighbor_weight": 1.0,
        "memory_size": 1024,
        "n_bins": 5,
        "min_angle": 20.0,
    },
}


def merge_config(config: Mapping[str, Any] | None = None, **overrides: Any) -> dict[str, Any]:
    """Full configuration: :data:`DEFAULT_CONFIG` updated group by group with ``config`` then ``overrides``.

    Raises:
        KeyError: an unknown group or key (typos fail loudly).
    """
    merged = copy.deepcopy(DEFAULT_CONFIG)
    for source in (config or {}, overrides):
        for group, value in source.items():
            if group not in merged:
                raise KeyError(f"unknown model config group {group!r}; known: {sorted(merged)}")
            if group == "image_size":
                merged[group] = int(value)
            elif value is None:
                if group != "background":
                    raise KeyError(f"only the background model can be disabled (None), not {group!r}")
                merged[group] = None
            else:
                base = merged[group] if merged[group] is not None else copy.deepcopy(DEFAULT_CONFIG[group])
                for key, v in dict(value).items():
                    if key not in base:
                        raise KeyError(f"unknown key {key!r} in model config group {group!r}; known: {sorted(base)}")
                    base[key] = dict(v) if isinstance(v, Mapping) else v
                merged[group] = base
    return merged


def unicorn_config(family: str = "real", size: str = "small", **overrides: Any) -> dict[str, Any]:
    """The reference's settings for a dataset family (``"real"`` or ``"shapenet"``) and model size.

    ``"real"``: CompCars / CUB / LSUN / Pascal3D+ (ellipsoid scale 0.6, background model, elevation
    [-10, 30], roll [-30, 30], translation and scale ranges 0.3). ``"shapenet"``: scale 0.4, field width 512,
    no background, elevation 30 and roll 0 fixed, T range (0.2, 0.2, 0), scale range 0.5, 50 faces per pixel.
    ``"big"``: four encoders and the big code sizes / generator widths.
    """
    if family not in ("real", "shapenet") or size not in ("small", "big"):
        raise ValueError(f"family must be 'real' or 'shapenet' and size 'small' or 'big', got {family!r}, {size!r}")
    big = size == "big"
    cfg: dict[str, Any] = {
        "encoder": {"shared": not big},
        "shape": {"code_dim": 64 if big else 32},
        "texture": {"code_dim": 512 if big else 128, "min_features": 64 if big else 16},
        "background": {"code_dim": 256 if big else 128, "min_features": 64 if big else 16},
    }
    if family == "shapenet":
        cfg["template"] = {"scale": 0.4}
        cfg["shape"]["n_field_units"] = 512
        cfg["background"] = None
        cfg["pose"] = {
            "elev_range": (30.0, 30.0),
            "roll_range": (0.0, 0.0),
            "T_range": (0.2, 0.2, 0.0),
            "scale_range": 0.5,
        }
        cfg["renderer"] = {
            "fov": None,
            "focal_length": 3.732050895690918,
            "options": {"sigma": 1e-4, "faces_per_pixel": 50},
        }
    return merge_config(merge_config(cfg), **overrides)


@dataclass
class Prediction:
    """Everything the model predicts for a batch of B images.

    Attributes:
        shape_code: (B, Cs) masked shape codes.
        texture_code: (B, Ct) masked texture codes.
        background_code: (B, Cb) masked background codes, or None without a background model.
        canonical_verts: (B, V, 3) deformed template ``template + displacement`` (before scaling).
        scale: (B, 3) anisotropic scales.
        verts: (B, V, 3) world-space mesh ``scale * canonical_verts``.
        texture: (B, 3, Ht, Wt) UV texture images in [0, 1].
        background: (B, 3, H, W) background images in [0, 1], or None.
        poses: all K pose candidates (:class:`PoseOutput`, candidate-major).
        R: (B, 3, 3) and T: (B, 3): the most likely candidate.
    """

    shape_code: torch.Tensor
    texture_code: torch.Tensor
    background_code: torch.Tensor | None
    canonical_verts: torch.Tensor
    scale: torch.Tensor
    verts: torch.Tensor
    texture: torch.Tensor
    background: torch.Tensor | None
    poses: PoseOutput
    R: torch.Tensor
    T: torch.Tensor


def _mean_texture(maps: torch.Tensor) -> torch.Tensor:
    """Replace every texture image by its mean colour: (B, C, H, W) -> (B, C, H, W)."""
    return maps.mean(dim=(2, 3), keepdim=True).expand_as(maps)


class Unicorn(nn.Module):
    """The structured autoencoder (see the module docstring for the configuration keys).

    Args:
        config: configuration mapping (groups as in :data:`DEFAULT_CONFIG`); keyword groups override it.

    Example:
        >>> model = Unicorn(unicorn_config("real", image_size=32, loss={"perceptual": None}))
        >>> pred = model.predict(torch.rand(2, 3, 32, 32))
        >>> tuple(pred.verts.shape), tuple(pred.texture.shape)
        ((2, 642, 3), (2, 3, 64, 64))
    """

    def __init__(self, config: Mapping[str, Any] | None = None, **groups: Any) -> None:
        super().__init__()
        cfg = merge_config(config, **groups)
        self.config = cfg
        size = cfg["image_size"]
        if size < 8:
            raise ValueError(f"image_size must be >= 8, got {size}")

        self.template = TemplateMesh(**cfg["template"])

        n_enc = 1 if cfg["encoder"]["shared"] else (4 if cfg["background"] is not None else 3)
        self.encoders = nn.ModuleList([ResNet18() for _ in range(n_enc)])
        nf = ResNet18.out_features

        sh = dict(cfg["shape"])
        sh_active = sh.pop("active_dims")
        self.shape = ShapeHead(nf, **sh)
        self.shape.mask.set_active_dims(sh_active)

        tx = dict(cfg["texture"])
        self.texture = CodeGenerator(
            nf,
            tx["code_dim"],
            tx["size"],
            tx["min_features"],
            tx["n_reg_units"],
            tx["n_reg_layers"],
            tx["active_dims"],
        )
        self.background: CodeGenerator | None = None
        if cfg["background"] is not None:
            bg = cfg["background"]
            self.background = CodeGenerator(
                nf,
                bg["code_dim"],
                size,
                bg["min_features"],
                bg["n_reg_units"],
                bg["n_reg_layers"],
                bg["active_dims"],
            )

        po = dict(cfg["pose"])
        scale_range = po.pop("scale_range")
        self.pose = PoseHead(nf, **po)
        self.scale = ScaleHead(nf, scale_range, po["n_units"], po["n_layers"])

        rd = cfg["renderer"]
        if rd["composite"] not in ("direct", "reference"):
            raise ValueError(f"renderer.composite must be 'direct' or 'reference', got {rd['composite']!r}")
        camera = PerspectiveCamera(fov=rd["fov"], focal_length=rd["focal_length"])
        self.renderer = build_renderer(
            rd["name"],
            image_size=size,
            camera=camera,
            background_color=tuple(rd["background_color"]),
            **dict(rd["options"] or {}),
        )

        ls = cfg["loss"]
        self.perceptual: nn.Module | None
        if ls["perceptual"] == "vgg":
            self.perceptual = VGGPerceptualLoss(ls["vgg_weights"])
        elif ls["perceptual"] == "structural":
            self.perceptual = StructuralLoss()
        elif ls["perceptual"] is None:
            self.perceptual = None
        else:
            raise ValueError(f"loss.perceptual must be 'vgg', 'structural' or None, got {ls['perceptual']!r}")
        if ls["pose_objective"] not in POSE_OBJECTIVES:
            raise ValueError(f"loss.pose_objective must be one of {POSE_OBJECTIVES}, got {ls['pose_objective']!r}")
        self.normal_loss = NormalConsistencyLoss(self.template.faces)
        self.laplacian_loss = UniformLaplacianLoss(self.template.faces, self.template.num_verts)
        self.memory = NeighborMemory(ls["memory_size"], ls["n_bins"], ls["min_angle"])

    # ------------------------------------------------------------------ configuration at run time
    @property
    def n_candidates(self) -> int:
        return self.pose.n_candidates

    def set_active_dims(
        self, shape: int | None = None, texture: int | None = None, background: int | None = None
    ) -> None:
        """Change the number of active code dimensions (progressive conditioning); None leaves one as is."""
        if shape is not None:
            self.shape.mask.set_active_dims(shape)
        if texture is not None:
            self.texture.mask.set_active_dims(texture)
        if background is not None and self.background is not None:
            self.background.mask.set_active_dims(background)

    def active_dims(self) -> dict[str, int]:
        """Current active code sizes."""
        dims = {"shape": self.shape.mask.active_dims, "texture": self.texture.mask.active_dims}
        if self.background is not None:
            dims["background"] = self.background.mask.active_dims
        return dims

    def set_stage_switches(
        self, translation: bool | None = None, deformation: bool | None = None, scale: bool | None = None
    ) -> None:
        """Enable or hold off (stage-1 curriculum) the translation offsets, the deformation and the scale."""
        if translation is not None:
            self.pose.use_translation.fill_(bool(translation))
        if deformation is not None:
            self.shape.use_deformation.fill_(bool(deformation))
        if scale is not None:
            self.scale.use_scale.fill_(bool(scale))

    # ------------------------------------------------------------------ forward pieces
    def _check_images(self, images: torch.Tensor) -> None:
        s = self.config["image_size"]
        if images.dim() != 4 or images.shape[1:] != (3, s, s):
            raise ValueError(f"images must have shape (B, 3, {s}, {s}), got {tuple(images.shape)}")

    def _encode(self, images: torch.Tensor, branches: tuple[str, ...]) -> dict[str, torch.Tensor]:
        """Encoder features (B, 512) of the requested branches (one shared encoder or one per branch)."""
        if len(self.encoders) == 1:
            f = self.encoders[0](images)
            return {b: f for b in branches}
        return {b: self.encoders[BRANCHES.index(b)](images) for b in branches}

    def _branches(self) -> tuple[str, ...]:
        return BRANCHES if self.background is not None else BRANCHES[:3]

    def _predict_3d(
        self, feats: dict[str, torch.Tensor], average_texture: bool
    ) -> tuple[
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
        torch.Tensor,
        torch.Tensor | None,
        torch.Tensor | None,
    ]:
        """Shape code, canonical verts, scale, texture code, texture, background code, background."""
        z_sh = self.shape.code(feats["shape"])
        canonical = self.template.verts + self.shape(self.template.verts, z_sh)
        scale = self.scale(feats["shape"])
        z_tx = self.texture.code(feats["texture"])
        maps = self.texture(z_tx)
        if average_texture:
            maps = _mean_texture(maps)
        z_bg = bkg = None
        if self.background is not None:
            z_bg = self.background.code(feats["background"])
            bkg = self.background(z_bg)
        return z_sh, canonical, scale, z_tx, maps, z_bg, bkg

    def predict(self, images: torch.Tensor, average_texture: bool = False) -> Prediction:
        """Predict everything for a batch (B, 3, S, S) of [0, 1] images (gradients kept)."""
        self._check_images(images)
        feats = self._encode(images, self._branches())
        z_sh, canonical, scale, z_tx, maps, z_bg, bkg = self._predict_3d(feats, average_texture)
        poses = self.pose(feats["pose"])
        R, T = poses.select()
        return Prediction(
            shape_code=z_sh,
            texture_code=z_tx,
            background_code=z_bg,
            canonical_verts=canonical,
            scale=scale,
            verts=canonical * scale.unsqueeze(1),
            texture=maps,
            background=bkg,
            poses=poses,
            R=R,
            T=T,
        )

    def textures(self, maps: torch.Tensor) -> TexturesUV:
        """UV textures of the template for texture images (B, 3, Ht, Wt)."""
        wrap = self.template.wrap_u
        return TexturesUV(maps, self.template.face_uvs, wrap_u=wrap, align_corners=not wrap)

    def render(
        self,
        verts: torch.Tensor,
        maps: torch.Tensor,
        R: torch.Tensor,
        T: torch.Tensor,
        background: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Render textured meshes over their backgrounds.

        Args:
            verts: (N, V, 3) world vertices; maps: (N, 3, Ht, Wt); R: (N, 3, 3); T: (N, 3);
            background: (N, 3, S, S) or None (renderer's background colour).

        Returns:
            rgb (N, 3, S, S) and alpha (N, 1, S, S).
        """
        faces = self.template.faces
        if self.config["renderer"]["composite"] == "direct" or background is None:
            out = self.renderer(verts, faces, self.textures(maps), R=R, T=T, background=background)
            return out[:, :3], out[:, 3:]
        out = self.renderer(verts, faces, self.textures(maps), R=R, T=T)
        rgb, alpha = out[:, :3], out[:, 3:]
        return rgb * alpha + (1 - alpha) * background, alpha

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, Prediction]:
        """Reconstruct images (B, 3, S, S) with the most likely pose: ``(rec (B, 3, S, S), prediction)``."""
        pred = self.predict(images)
        rec, _ = self.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
        return rec, pred

    # ------------------------------------------------------------------ losses
    def reconstruction_terms(self, rec: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
        """Weighted per-sample terms ``{"rgb": (N,), "perceptual": (N,)}`` (perceptual only if enabled)."""
        ls = self.config["loss"]
        terms = {}
        # like the reference, a weight <= 0 drops the term entirely
        if ls["rgb_weight"] > 0:
            terms["rgb"] = ls["rgb_weight"] * mse_per_sample(rec, target)
        if self.perceptual is not None and ls["perceptual_weight"] > 0:
            terms["perceptual"] = ls["perceptual_weight"] * self.perceptual(rec, target)
        return terms

    def pose_step(self, images: torch.Tensor, average_texture: bool = False) -> dict[str, torch.Tensor]:
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
            and the reconstruction terms probability-weighted like the total, so that they sum to ``total``.
        """
        self._check_images(images)
        branches = self._branches()
        shared = len(self.encoders) == 1
        feats = self._encode(images, ("pose",) if not shared else branches)
        with torch.no_grad():
            # detached 3D branches: computing them without autograd is the same and cheaper
            other = feats if shared else self._encode(images, tuple(b for b in branches if b != "pose"))
            other = {k: v.detach() for k, v in other.items()}
            _, canonical, scale, _, maps, _, bkg = self._predict_3d(other, average_texture)
            verts = canonical * scale.unsqueeze(1)
        poses = self.pose(feats["pose"])
        K, B = poses.probs.shape
        R, T = poses.flat()
        rec, _ = self.render(
            verts.repeat(K, 1, 1),
            maps.repeat(K, 1, 1, 1),
            R,
            T,
            None if bkg is None else bkg.repeat(K, 1, 1, 1),
        )
        terms = self.reconstruction_terms(rec, images.repeat(K, 1, 1, 1))
        ls = self.config["loss"]
        assigned = ls["pose_objective"] == "assigned"
        weights = poses.probs.detach() if assigned else poses.probs
        out = {name: (weights * value.view(K, B)).sum(0).mean() for name, value in terms.items()}
        if assigned and terms:
            per_candidate = torch.stack(list(terms.values())).sum(0).view(K, B)
            out["assignment"] = ls["assignment_weight"] * candidate_assignment_loss(poses.log_probs, per_candidate)
        if ls["uniform_weight"] > 0:
            out["uniform"] = ls["uniform_weight"] * uniform_pose_prior(poses.probs, ls["uniform_reduction"])
        out["total"] = torch.stack(list(out.values())).sum() if out else images.new_zeros(())
        return out

    def step_3d(self, images: torch.Tensor, average_texture: bool = False) -> dict[str, torch.Tensor]:
        """3D-step: the most likely candidate rendered with a detached pose.

        ``total = mean_b [L_rec + w_nbr * L_nbr] + w_norm * L_norm + w_lap * L_lap`` (``*_weight`` keys);
        gradients reach the shape, scale, texture and background branches (and their encoders) only.
        The neighbour term is active once both the shape and texture codes have active dimensions.

        Args:
            images: (B, 3, S, S) in [0, 1].
            average_texture: replace every texture by its mean colour (drawn once per batch by the trainer).

        Returns:
            weighted scalars ``total``, ``rgb``, ``perceptual`` (if enabled), ``normal``, ``laplacian`` and
            ``neighbor`` (when active); they sum to ``total``.
        """
        self._check_images(images)
        branches = self._branches()
        shared = len(self.encoders) == 1
        feats = self._encode(images, branches if shared else tuple(b for b in branches if b != "pose"))
        with torch.no_grad():
            pose_feats = feats["pose"] if shared else self._encode(images, ("pose",))["pose"]
            R, T = self.pose(pose_feats.detach()).select()
        z_sh, canonical, scale, z_tx, maps, _, bkg = self._predict_3d(feats, average_texture)
        verts = canonical * scale.unsqueeze(1)
        rec, _ = self.render(verts, maps, R, T, bkg)
        per_sample = self.reconstruction_terms(rec, images)
        ls = self.config["loss"]
        use_nbr = ls["neighbor_weight"] > 0 and self.shape.mask.active_dims > 0 and self.texture.mask.active_dims > 0
        if use_nbr:
            per_sample["neighbor"] = ls["neighbor_weight"] * self.neighbor_loss(
                images, z_sh, z_tx, canonical, maps, R, average_texture
            )
        out = {name: value.mean() for name, value in per_sample.items()}
        if ls["normal_weight"] > 0:
            out["normal"] = ls["normal_weight"] * self.normal_loss(verts)
        if ls["laplacian_weight"] > 0:
            out["laplacian"] = ls["laplacian_weight"] * self.laplacian_loss(verts)
        out["total"] = torch.stack(list(out.values())).sum() if out else images.new_zeros(())
        return out

    def neighbor_loss(
        self,
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
        self_index = self.memory.push(images, shape_code, texture_code, R)
        match = self.memory.search(shape_code.detach(), texture_code.detach(), R, self_index)
        loss = images.new_zeros(B)
        # a host sync: the swaps run on the samples that found neighbours only (all of them once the memory
        # holds a few batches); padding the others would change the neighbour batch's BatchNorm statistics
        idx = match.valid.nonzero().squeeze(1)
        if idx.numel() == 0:
            return loss
        nbr_images = torch.cat(
            [self.memory.images[match.shape_index[idx]], self.memory.images[match.texture_index[idx]]]
        )
        n = idx.numel()
        with torch.no_grad():
            nbr_scale, nbr_maps, nbr_verts, nbr_R, nbr_T, nbr_bkg = self._neighbour_parameters(
                nbr_images, n, average_texture
            )
        verts = torch.cat([canonical_verts[idx] * nbr_scale.unsqueeze(1), nbr_verts])
        tex = torch.cat([nbr_maps, maps[idx]])
        rec, _ = self.render(verts, tex, nbr_R, nbr_T, nbr_bkg)
        terms = self.reconstruction_terms(rec, nbr_images)
        if not terms:
            return loss
        per = sum(terms.values())
        return loss.index_put((idx,), per[:n] + per[n:])

    def _neighbour_parameters(
        self, images: torch.Tensor, n: int, average_texture: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """What the two swaps take from the neighbours (call without gradient).

        ``images`` (2n, 3, S, S) holds the n shape neighbours then the n texture neighbours. The encoders see
        all 2n images together (their batch statistics are those of :meth:`predict` on the same batch); the
        heads compute only what a swap uses: the shape neighbours' scales (n, 3) and texture maps
        (n, 3, Ht, Wt), the texture neighbours' world vertices (n, V, 3), and everyone's R (2n, 3, 3),
        T (2n, 3) and background (2n, 3, S, S) or None.
        """
        feats = self._encode(images, self._branches())
        scale = self.scale(feats["shape"])
        z_sh = self.shape.code(feats["shape"][n:])
        verts = (self.template.verts + self.shape(self.template.verts, z_sh)) * scale[n:].unsqueeze(1)
        maps = self.texture(self.texture.code(feats["texture"][:n]))
        if average_texture:
            maps = _mean_texture(maps)
        bkg = None
        if self.background is not None:
            bkg = self.background(self.background.code(feats["background"]))
        R, T = self.pose(feats["pose"]).select()
        return scale[:n], maps, verts, R, T, bkg
