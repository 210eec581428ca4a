"""UNICORN's structured autoencoder: image -> (shape, texture, pose, background) -> rendered image.

The model is a plain ``nn.Module`` that predicts (:meth:`Unicorn.predict`, or its parts :meth:`Unicorn.encode`,
:meth:`Unicorn.predict_3d` and the pose head), decodes codes (:meth:`Unicorn.decode`, which the training steps
and the refinement share) and renders (:meth:`Unicorn.render`); it holds no training state.
The training objectives (pose step, 3D step, neighbour loss and its memory) are :mod:`unicorn.objectives`'s. A
trainer drives the progressive code sizes and stage-1 switches with :meth:`Unicorn.set_active_dims` and
:meth:`Unicorn.set_stage_switches`.

The mesh is computed in one place each: the canonical mesh ``template + deformation(shape code)`` by
:meth:`Unicorn.deform`, the world mesh ``scale * canonical`` by :func:`world_verts`.

Configuration: a mapping of groups (image size, encoder, template, shape, texture, background, pose,
renderer, loss), merged over the defaults; every key, default, range and allowed value is in
:mod:`unicorn.model.config`, the presets (model sizes, dataset families) are ``conf/``'s YAML files
(:func:`unicorn.config.model_preset`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from unicorn.checks import check_pixels, check_shape
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.model.compositing import build_compositing
from unicorn.model.config import BRANCHES, CODE_BRANCHES, merge_config, model_branches
from unicorn.model.encoder import ResNet18
from unicorn.model.field import ShapeHead
from unicorn.model.generator import CodeGenerator, mean_texture
from unicorn.model.pose import PoseHead, PoseOutput, ScaleHead
from unicorn.model.template import TemplateMesh
from unicorn.render import TexturesUV, build_renderer
from unicorn.render.settings import buffer_color

__all__ = [
    "BRANCHES",
    "Prediction",
    "Prediction3D",
    "Unicorn",
    "build_networks",
    "encoder_index",
    "world_verts",
]


def world_verts(canonical_verts: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The world-space mesh (B, V, 3) ``scale * canonical``: canonical vertices (B, V, 3), anisotropic scales (B, 3)."""
    return canonical_verts * scale.unsqueeze(1)


@dataclass
class Prediction3D:
    """What the 3D branches predict for a batch of B images (:meth:`Unicorn.predict_3d`; no pose).

    Attributes:
        shape_code: (B, Cs) masked shape codes.
        canonical_verts: (B, V, 3) deformed template (:meth:`Unicorn.deform`).
        scale: (B, 3) anisotropic scales.
        texture_code: (B, Ct) masked texture codes.
        texture: (B, 3, Ht, Wt) UV texture images in [0, 1].
        background_code: (B, Cb) masked background codes, or None without a background model.
        background: (B, 3, S, S) background images in [0, 1], or None.
    """

    shape_code: torch.Tensor
    canonical_verts: torch.Tensor
    scale: torch.Tensor
    texture_code: torch.Tensor
    texture: torch.Tensor
    background_code: torch.Tensor | None
    background: torch.Tensor | None

    @property
    def verts(self) -> torch.Tensor:
        """(B, V, 3) world-space mesh (:func:`world_verts`)."""
        return world_verts(self.canonical_verts, self.scale)


@dataclass
class Prediction:
    """Everything the model predicts for a batch of B images.

    Attributes:
        shape_code: (B, Cs) masked shape codes.
        texture_code: (B, Ct) masked texture codes.
        background_code: (B, Cb) masked background codes, or None without a background model.
        canonical_verts: (B, V, 3) deformed template ``template + displacement`` (before scaling).
        scale: (B, 3) anisotropic scales.
        verts: (B, V, 3) world-space mesh ``scale * canonical_verts`` (:func:`world_verts`).
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


def encoder_index(cfg: Mapping[str, Any]) -> dict[str, int]:
    """Which of the model's encoders each branch reads, for a merged configuration: the big model's one per
    branch in :data:`BRANCHES` order (``encoder.shared`` false); otherwise encoder 0, shared, for every branch
    but those of ``encoder.own``, which read encoders 1, 2, ... in :data:`BRANCHES` order."""
    branches = model_branches(cfg["background"] is not None)
    if not cfg["encoder"]["shared"]:
        return {b: i for i, b in enumerate(branches)}
    own = [b for b in branches if b in cfg["encoder"]["own"]]
    return {b: 1 + own.index(b) if b in own else 0 for b in branches}


def build_networks(cfg: Mapping[str, Any]) -> dict[str, nn.Module | None]:
    """The learned networks of a merged configuration: encoders, shape, texture, background, pose and scale heads
    (the only parts whose size grows with the configuration: :func:`unicorn.model.size.count_parameters` builds
    them on no memory)."""
    n_enc = 1 + max(encoder_index(cfg).values())
    enc = cfg["encoder"]
    encoders = nn.ModuleList([ResNet18(enc["width"], cfg["image_size"], enc["pooled"]) for _ in range(n_enc)])
    nf = encoders[0].out_features

    sh = dict(cfg["shape"])
    sh_active = sh.pop("active_dims")
    shape = ShapeHead(nf, **sh)
    shape.mask.set_active_dims(sh_active)

    tx = dict(cfg["texture"])
    texture = CodeGenerator(
        nf,
        tx["code_dim"],
        tx["size"],
        tx["min_features"],
        tx["n_reg_units"],
        tx["n_reg_layers"],
        tx["active_dims"],
        tx["symmetric"],
    )
    background = None
    if cfg["background"] is not None:
        bg = cfg["background"]
        background = CodeGenerator(
            nf,
            bg["code_dim"],
            cfg["image_size"],
            bg["min_features"],
            bg["n_reg_units"],
            bg["n_reg_layers"],
            bg["active_dims"],
        )

    po = dict(cfg["pose"])
    scale_range = po.pop("scale_range")
    pose = PoseHead(nf, **po)
    scale = ScaleHead(nf, scale_range, po["n_units"], po["n_layers"])
    return {
        "encoders": encoders,
        "shape": shape,
        "texture": texture,
        "background": background,
        "pose": pose,
        "scale": scale,
    }


def _config_follows_background_color(model: Unicorn, incompatible_keys: Any) -> None:
    """``load_state_dict``'s post hook: ``config["renderer"]["background_color"]`` takes the value of the
    renderer's ``background_color`` buffer (3,), which the loaded weights may have changed, so that the config
    describes what the model renders and a config saved beside the weights agrees with them
    (:func:`~unicorn.render.settings.buffer_color`: the colour as written while the buffer holds it)."""
    buffer = getattr(model.renderer, "background_color", None)
    if not isinstance(buffer, torch.Tensor) or buffer.shape != (3,):  # a plugin renderer without the buffer
        return
    renderer = model.config["renderer"]
    color = buffer_color(buffer, renderer["background_color"])
    if color != tuple(renderer["background_color"]):
        renderer["background_color"] = color


class Unicorn(nn.Module):
    """The structured autoencoder (see the module docstring for the configuration keys).

    Args:
        config: configuration mapping (groups as in :data:`unicorn.model.config.DEFAULT_CONFIG`); keyword groups
            override it. :attr:`config` keeps the merged mapping the model was built from: its ``active_dims`` are
            the code sizes at build time, while the sizes in force are buffers, saved with the weights, that
            :meth:`set_active_dims` changes and :meth:`active_dims` reads.

    Raises:
        KeyError, ValueError: an unknown key, a value out of range or not allowed (named).

    Example:
        >>> model = Unicorn(image_size=32)
        >>> pred = model.predict(torch.rand(2, 3, 32, 32))
        >>> tuple(pred.verts.shape), tuple(pred.texture.shape)
        ((2, 642, 3), (2, 3, 64, 64))
    """

    encoders: nn.ModuleList
    shape: ShapeHead
    texture: CodeGenerator
    background: CodeGenerator | None
    pose: PoseHead
    scale: ScaleHead

    def __init__(self, config: Mapping[str, Any] | None = None, **groups: Any) -> None:
        super().__init__()
        cfg = merge_config(config, **groups)
        self.config = cfg
        size = cfg["image_size"]

        self.template = TemplateMesh(**cfg["template"])

        for name, module in build_networks(cfg).items():  # encoders, shape, texture, background, pose, scale
            setattr(self, name, module)
        self.encoder_index = encoder_index(cfg)

        rd = cfg["renderer"]
        camera = PerspectiveCamera(fov=rd["fov"], focal_length=rd["focal_length"])
        self.renderer = build_renderer(
            rd["name"],
            image_size=size,
            camera=camera,
            background_color=tuple(rd["background_color"]),
            **dict(rd["options"] or {}),
        )

        self.compositing = build_compositing(rd["composite"])
        # the colour is also a buffer of the renderer, loaded with the weights: the config follows it
        self.register_load_state_dict_post_hook(_config_follows_background_color)

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
        heads = {branch: getattr(self, branch) for branch in CODE_BRANCHES}
        return {branch: head.mask.active_dims for branch, head in heads.items() if head is not None}

    def set_stage_switches(
        self,
        translation: bool | None = None,
        deformation: bool | None = None,
        scale: bool | None = None,
        elevation_roll: bool | None = None,
    ) -> None:
        """Enable or hold off (stage-1 curriculum) the translation offsets, the deformation, the scale and the
        elevation and roll offsets; None leaves one as is."""
        if translation is not None:
            self.pose.use_translation.fill_(bool(translation))
        if elevation_roll is not None:
            self.pose.use_elevation_roll.fill_(bool(elevation_roll))
        if deformation is not None:
            self.shape.use_deformation.fill_(bool(deformation))
        if scale is not None:
            self.scale.use_scale.fill_(bool(scale))

    # ------------------------------------------------------------------ forward pieces
    def check_images(self, images: torch.Tensor) -> None:
        """Raise unless ``images`` is (B, 3, S, S) with S the model's image size, of the weights' dtype.

        Raises:
            ShapeError: another shape.
            TypeError: another dtype; the message says how to convert (uint8 pixels: divide by 255).
        """
        s = self.config["image_size"]
        check_shape(images, "B, 3, S, S", "images", {"S": s})
        dtype = self.template.verts.dtype
        if images.dtype != dtype:
            if images.dtype == torch.bool:  # a mask: True reads as 1
                hint = f" (images.to({dtype}) converts it: the model reads [0, 1])"
            elif not images.is_floating_point():
                hint = f" (pixels in [0, 255]: images.to({dtype}) / 255, the model reads [0, 1])"
            else:
                hint = f" (images.to({dtype}) converts it)"
            raise TypeError(f"images must be {dtype}, the model's dtype, got {images.dtype}{hint}")

    def encode(self, images: torch.Tensor, branches: tuple[str, ...]) -> dict[str, torch.Tensor]:
        """Encoder features (B, 8 x width; 512 for ResNet-18) of the requested branches; each encoder they read
        (:func:`encoder_index`) runs once."""
        feats = {i: self.encoders[i](images) for i in sorted({self.encoder_index[b] for b in branches})}
        return {b: feats[self.encoder_index[b]] for b in branches}

    def encoder_mates(self, branch: str) -> tuple[str, ...]:
        """The other branches that read ``branch``'s encoder (none when it has its own)."""
        i = self.encoder_index[branch]
        return tuple(b for b in self.branches() if b != branch and self.encoder_index[b] == i)

    def branches(self) -> tuple[str, ...]:
        """The branches this model predicts: shape, texture, pose, and background when it has one."""
        return model_branches(self.background is not None)

    def deform(self, shape_code: torch.Tensor) -> torch.Tensor:
        """The canonical mesh (B, V, 3): the template deformed by the shape field for masked codes (B, Cs)."""
        return self.template.verts + self.shape(self.template.verts, shape_code)

    def decode(
        self,
        shape_code: torch.Tensor,
        texture_code: torch.Tensor,
        background_code: torch.Tensor | None = None,
        average_texture: bool | torch.Tensor = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """What masked codes describe: the canonical mesh (B, V, 3) of shape codes (B, Cs), the texture images
        (B, 3, Ht, Wt) of texture codes (B, Ct) and the backgrounds (B, 3, S, S) of background codes (B, Cb), None
        without them or without a background model. Each code is decoded on its own: the three batches may differ.

        Args:
            average_texture: replace every texture by its mean colour; a 0-dim bool tensor selects on the device
                (a compiled training step's choice: one graph for both values, where a Python bool is guarded on).
        """
        canonical = self.deform(shape_code)
        maps = self.texture(texture_code)
        if isinstance(average_texture, torch.Tensor):
            maps = torch.where(average_texture, mean_texture(maps), maps)
        elif average_texture:
            maps = mean_texture(maps)
        bkg = None
        if self.background is not None and background_code is not None:
            bkg = self.background(background_code)
        return canonical, maps, bkg

    def predict_3d(self, feats: dict[str, torch.Tensor], average_texture: bool | torch.Tensor = False) -> Prediction3D:
        """The 3D branches (shape, scale, texture, background) from encoder features (:meth:`encode`), each (B, F):
        the codes regressed from them, decoded by :meth:`decode`.

        Args:
            feats: the ``"shape"``, ``"texture"`` (and ``"background"``) features.
            average_texture: replace every texture by its mean colour.
        """
        z_sh = self.shape.code(feats["shape"])
        z_tx = self.texture.code(feats["texture"])
        z_bg = None if self.background is None else self.background.code(feats["background"])
        canonical, maps, bkg = self.decode(z_sh, z_tx, z_bg, average_texture)
        return Prediction3D(z_sh, canonical, self.scale(feats["shape"]), z_tx, maps, z_bg, bkg)

    def predict(self, images: torch.Tensor, average_texture: bool = False) -> Prediction:
        """Predict everything for a batch (B, 3, S, S) of [0, 1] images (gradients kept).

        Args:
            images: (B, 3, S, S) floating point pixels in [0, 1], of the model's dtype.
            average_texture: replace every texture map by its mean colour (as the training's first iterations
                render them, ``schedule.texture_averaging``).

        Raises:
            ShapeError, TypeError: see :meth:`check_images`.
            ValueError: values out of [0, 1] (:func:`unicorn.checks.check_pixels`).
        """
        self.check_images(images)
        check_pixels(images)
        feats = self.encode(images, self.branches())
        p = self.predict_3d(feats, average_texture)
        poses = self.pose(feats["pose"])
        R, T = poses.select()
        return Prediction(
            shape_code=p.shape_code,
            texture_code=p.texture_code,
            background_code=p.background_code,
            canonical_verts=p.canonical_verts,
            scale=p.scale,
            verts=p.verts,
            texture=p.texture,
            background=p.background,
            poses=poses,
            R=R,
            T=T,
        )

    def textures(self, maps: torch.Tensor) -> TexturesUV:
        """UV textures of the template for texture images (B, 3, Ht, Wt).

        Raises:
            ShapeError: maps of another shape (channels last: ``maps.permute(0, 3, 1, 2)``).
            TypeError: maps that are not floating point.
        """
        # the renderer takes any channel count: (B, Ht, Wt, 3) maps would render Ht channels against an RGB
        # background and fail there, naming the background
        check_shape(maps, "B, 3, Ht, Wt", "maps", floating=True)
        wrap = self.template.wrap_u
        return TexturesUV(maps, self.template.face_uvs, wrap_u=wrap, align_corners=not wrap, channels_last=False)

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
            background: (N, 3, S, S) or None (renderer's background colour); put under the object by the
                configured compositing (``renderer.composite``, :mod:`unicorn.model.compositing`).

        Returns:
            rgb (N, 3, S, S) and alpha (N, 1, S, S).

        Raises:
            ShapeError, TypeError: maps of another shape or dtype (:meth:`textures`); the renderer checks the rest.
        """
        return self.compositing(self.renderer, verts, self.template.faces, self.textures(maps), R, T, background)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, Prediction]:
        """Reconstruct images (B, 3, S, S) with the most likely pose: ``(rec (B, 3, S, S), prediction)``."""
        pred = self.predict(images)
        rec, _ = self.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
        return rec, pred
