"""The model's configuration, defined once: typed groups with their defaults, ranges and allowed values.

:class:`UnicornConfig` is what :class:`unicorn.model.Unicorn` takes (as the plain mapping
:data:`DEFAULT_CONFIG` / :func:`merge_config`); the training schema (:mod:`unicorn.config.schema`) reuses the
same group classes for its ``model`` group, and the presets (small, big, tiny; real-image and ShapeNet families)
are the YAML files of ``conf/`` (:func:`unicorn.config.model_preset`). Every value check of a model
configuration is :func:`check_model_config`, run by :func:`merge_config` and by the training config's validation,
but for the ``loss`` group's names of a registered loss, which the training floor checks
(:func:`unicorn.objectives.loss_factory.check_loss_choices`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import typing
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from numbers import Integral
from typing import Any

from unicorn.model.ranges import ModelConfigError, check_ranges, ranged
from unicorn.render.settings import BACKGROUND_COLOR, DEFAULT_SETTINGS

__all__ = [
    "DEFAULT_CONFIG",
    "BRANCHES",
    "BackgroundConfig",
    "CHOICES",
    "CODE_BRANCHES",
    "EncoderConfig",
    "LOSS_KEYS",
    "LossConfig",
    "ModelConfigError",
    "ModelGroups",
    "PoseConfig",
    "RendererConfig",
    "ShapeConfig",
    "TemplateConfig",
    "TextureConfig",
    "UnicornConfig",
    "allowed_values",
    "check_model_config",
    "merge_config",
    "model_branches",
]

#: the model's branches, in the order of its encoders when each has its own (the big model); the background is
#: last: a model without a background model has the first three
BRANCHES = ("shape", "texture", "pose", "background")
#: the branches with a latent code regressed from the image, whose active size grows stage by stage: all but the
#: pose, whose candidates and their probabilities are regressed directly (no code to grow)
CODE_BRANCHES = tuple(branch for branch in BRANCHES if branch != "pose")


def model_branches(has_background: bool) -> tuple[str, ...]:
    """The branches of a model with or without a background model (:data:`BRANCHES` ends with the background)."""
    return BRANCHES if has_background else BRANCHES[:-1]


# The settings that name a registered constructor take their allowed values from its registry, looked up when a
# configuration is checked: the registries' modules import torch, which this module does not need.


def _compositings() -> tuple[str, ...]:
    from unicorn.model.compositing import list_compositings

    return tuple(list_compositings())


#: allowed values of the model's string settings: ``group.key`` -> the values, or a function listing a registry's
#: names (:func:`allowed_values` resolves both). The ``loss`` settings that name a training loss (perceptual loss,
#: pose objective, viewpoint supervision) are checked against the training floor's registries by
#: :func:`unicorn.objectives.loss_factory.check_loss_choices`.
CHOICES: dict[str, tuple[Any, ...] | Callable[[], tuple[Any, ...]]] = {
    "template.uv_mode": ("seamless", "reference"),
    "renderer.composite": _compositings,
    "loss.uniform_reduction": ("sum", "mean"),
}


def allowed_values(key: str) -> tuple[Any, ...]:
    """The allowed values of the string setting ``key`` (``group.key`` of :data:`CHOICES`), registered ones
    included (e.g. a compositing added with :func:`unicorn.model.compositing.register_compositing`)."""
    allowed = CHOICES[key]
    return allowed() if callable(allowed) else allowed


#: the most rows of the neighbour memory (``loss.memory_size``; the reference's 1024): a row holds an image's codes
#: and pose, a few KB, so that the bound keeps the memory under a few GB
MAX_MEMORY_SIZE = 100_000


@dataclass
class EncoderConfig:
    shared: bool = True  # one ResNet-18 for all branches (False: one per branch, the big model)
    width: int = ranged(64, 1)  # channels of its first stage (64: ResNet-18; features are 8 x width)
    # with a shared encoder, the branches that read an encoder of their own instead (e.g. [background]); the
    # paper's models have none (small) or all (big, ``shared: false``)
    own: list[str] = field(default_factory=list)
    # the ResNet stages whose averaged outputs make the features, side by side (layer1 ... layer4); the paper's
    # features are the last stage's alone
    pooled: list[str] = field(default_factory=lambda: ["layer4"])


@dataclass
class TemplateConfig:
    level: int = ranged(3, 0, 7)  # icosphere subdivisions (3: 642 vertices)
    axes: tuple[float, float, float] = (1.0, 0.7, 0.7)
    scale: float = ranged(0.6, 1e-6)  # 0.6 real images, 0.4 ShapeNet
    uv_mode: str = "seamless"  # seamless | reference (see unicorn.model.template)
    bottom: float = ranged(1.0, 1e-3, 1)  # the lower half's height as a share of the upper's (1: an ellipsoid)


@dataclass
class ShapeConfig:
    code_dim: int = ranged(32, 1)
    active_dims: int = ranged(0, 0)
    n_field_units: int = ranged(128, 1)
    n_field_layers: int = ranged(2, 0)
    n_reg_units: int = ranged(128, 1)
    n_reg_layers: int = ranged(3, 0)
    # mirror-symmetric through the template's plane z = 0 (unicorn.model.field.ShapeHead); False: the paper, which
    # uses no symmetry prior
    symmetric: bool = False


@dataclass
class TextureConfig:
    code_dim: int = ranged(128, 1)
    active_dims: int = ranged(2, 0)
    size: int = ranged(64, 4)
    min_features: int = ranged(16, 1)
    n_reg_units: int = ranged(128, 1)
    n_reg_layers: int = ranged(3, 0)
    # mirror-symmetric maps (unicorn.model.generator.CodeGenerator; needs template.uv_mode=seamless and an even
    # size); False: the paper
    symmetric: bool = False


@dataclass
class BackgroundConfig:
    code_dim: int = ranged(128, 1)
    active_dims: int = ranged(4, 0)
    min_features: int = ranged(16, 1)
    n_reg_units: int = ranged(128, 1)
    n_reg_layers: int = ranged(3, 0)


@dataclass
class PoseConfig:
    n_elev: int = ranged(1, 1)
    n_azim: int = ranged(6, 1)
    azim_range: tuple[float, float] = (0.0, 360.0)
    elev_range: tuple[float, float] = (-10.0, 30.0)
    roll_range: tuple[float, float] = (-30.0, 30.0)
    T_range: Any = 0.3  # one float or (x, y, z)
    prior_translation: tuple[float, float, float] = (0.0, 0.0, 2.732)
    scale_range: Any = 0.3  # one float or (x, y, z)
    n_units: int = ranged(128, 1)
    n_layers: int = ranged(3, 0)


#: the backend options a model configuration names by default (the layered backend's that the presets set)
_LAYERED_OPTIONS = ("sigma", "faces_per_pixel", "perspective_correct")


@dataclass
class RendererConfig:
    """The model's renderer: a registered backend (:func:`unicorn.render.build_renderer`) and its camera.

    ``composite``: ``direct`` (the background image is the renderer's background) or ``reference`` (render
    over ``background_color``, then ``rgb * A + (1 - A) * bkg``, as the released models did).
    """

    name: str = "layered"
    fov: float | None = 30.0  # exactly one of fov and focal_length
    focal_length: float | None = None
    background_color: tuple[float, float, float] = BACKGROUND_COLOR
    composite: str = "direct"
    # the backend's options (the other keys of conf/renderer/<name>.yaml; unicorn.render.RenderSettings)
    options: dict[str, Any] = field(
        default_factory=lambda: {key: getattr(DEFAULT_SETTINGS, key) for key in _LAYERED_OPTIONS}
    )


@dataclass
class LossConfig:
    """The training objectives' settings (the ``loss`` group): carried in the model's configuration, so that a
    checkpoint keeps them, and read by :mod:`unicorn.objectives`, never by the model. Its names of a registered loss
    are checked there (:func:`unicorn.objectives.loss_factory.check_loss_choices`)."""

    rgb_weight: float = ranged(1.0, 0)
    perceptual: str | None = "vgg"  # vgg | structural | None
    perceptual_weight: float = ranged(10.0, 0)
    vgg_weights: str | None = None  # a copy of vgg16-397923af.pth; None: torch's hub cache (downloaded)
    normal_weight: float = ranged(0.01, 0)
    laplacian_weight: float = ranged(0.01, 0)
    uniform_weight: float = ranged(0.02, 0)
    uniform_reduction: str = "sum"  # sum (the paper) | mean (the reference code)
    # pose step: each pair of an image's candidates nearer than spacing_angle degrees costs up to spacing_weight
    # (unicorn.objectives.losses.candidate_spacing_loss); 0: left out (the paper)
    spacing_weight: float = ranged(0.0, 0)
    spacing_angle: float = ranged(30.0, 1, 180)
    # pose step: the candidates of each horizontally flipped image should mirror the image's own, x flip_weight
    # (unicorn.objectives.losses.flip_consistency_loss; one more pose-encoder pass a pose step); 0: left out (paper)
    flip_weight: float = ranged(0.0, 0)
    # pose step: the candidates of each image rolled by up to equivariance_roll degrees and shifted by up to
    # equivariance_shift (NDC) should be the image's own rolled and shifted alike, same azimuth, x equivariance_weight
    # (unicorn.objectives.losses.view_equivariance_loss; one more pose-encoder pass a pose step); 0: left out (paper)
    equivariance_weight: float = ranged(0.0, 0)
    equivariance_roll: float = ranged(15.0, 0, 90)
    equivariance_shift: float = ranged(0.1, 0, 1)
    # expected (the paper): the probability-weighted loss trains the probabilities; assigned: the reconstruction
    # terms are weighted by the detached probabilities and the probabilities learn from assignment_weight x the
    # cross-entropy against the best-reconstructing candidate (unicorn.objectives.losses.candidate_assignment_loss)
    pose_objective: str = "expected"
    assignment_weight: float = ranged(0.02, 0)
    # sampled (MagicPony's schedule; unicorn.objectives.pose_objectives.SampledCandidates): one candidate rendered per
    # image in both steps, random until sample_random_until, then the most likely for all but a share falling to
    # sample_random_share over sample_ramp iterations; uniform probabilities until sample_uniform_until; the rendered
    # candidate's score (-logit) regresses its loss x score_weight; temperature 1 / clip(it / sample_tau_period, 1, 100)
    score_weight: float = ranged(0.1, 0)
    sample_random_until: int = ranged(800, 0)
    sample_ramp: int = ranged(400, 0)
    sample_random_share: float = ranged(0.2, 0, 1)
    sample_uniform_until: int = ranged(400, 0)
    sample_tau_period: int = ranged(200, 1)
    # pose step: the pose branch also learns from the model's reconstructions rendered at drawn viewpoints
    # (unicorn.objectives.viewpoint; "renders"), or not (None, the paper): the cross-entropy toward the drawn view's
    # candidate x viewpoint_weight, its angles and translation regressed x viewpoint_pose_weight, from iteration
    # viewpoint_start at every viewpoint_every-th pose step, a share viewpoint_mix of the renders blending two images;
    # viewpoint_azimuth_only: only the azimuth drawn (elevation, roll and translation at the candidate's anchor)
    viewpoint: str | None = None
    viewpoint_weight: float = ranged(0.1, 0)
    viewpoint_pose_weight: float = ranged(0.1, 0)
    viewpoint_start: int = ranged(0, 0)
    viewpoint_every: int = ranged(1, 1)
    viewpoint_mix: float = ranged(0.5, 0, 1)
    viewpoint_azimuth_only: bool = False
    neighbor_weight: float = ranged(1.0, 0)
    memory_size: int = ranged(1024, 1, MAX_MEMORY_SIZE)
    n_bins: int = ranged(5, 1)
    min_angle: float = ranged(20.0, 0, 180)


#: the keys of the ``loss`` group: the options of the constructors it names (perceptual loss, pose objective,
#: viewpoint supervision), each of which takes its part of the group
LOSS_KEYS = tuple(f.name for f in dataclasses.fields(LossConfig))


@dataclass
class ModelGroups:
    """The groups the model and the training schema's ``model`` group share (the reference's small model)."""

    image_size: int = ranged(64, 8)  # input / render side
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    template: TemplateConfig = field(default_factory=TemplateConfig)
    shape: ShapeConfig = field(default_factory=ShapeConfig)
    texture: TextureConfig = field(default_factory=TextureConfig)
    background: BackgroundConfig | None = field(default_factory=BackgroundConfig)  # None: no background model
    pose: PoseConfig = field(default_factory=PoseConfig)
    loss: LossConfig = field(default_factory=LossConfig)


@dataclass
class UnicornConfig(ModelGroups):
    """Everything :class:`unicorn.model.Unicorn` takes."""

    renderer: RendererConfig = field(default_factory=RendererConfig)


#: the default configuration as a plain mapping (groups of keys), see :class:`UnicornConfig`
DEFAULT_CONFIG: dict[str, Any] = dataclasses.asdict(UnicornConfig())


def check_model_config(cfg: Mapping[str, Any], prefix: str = "") -> None:
    """All value checks of a model configuration (groups as :data:`DEFAULT_CONFIG`): ranges (whole numbers for the
    sizes and counts), on / off switches that are bools, choices and what the networks' constructors need (powers
    of 2 for the generated images, active code sizes within the codes, the pose and template vectors): the networks
    and the template are built from any configuration that passes (:func:`merge_config` makes its whole floats ints).

    Raises:
        ModelConfigError: the first bad value, named with its key (``prefix`` + ``group.key``).
    """
    check_ranges(cfg, UnicornConfig, prefix)
    _check_switches(cfg, prefix)
    for key in CHOICES:
        group, name = key.split(".")
        if cfg.get(group) is not None and cfg[group][name] not in (allowed := allowed_values(key)):
            raise ModelConfigError(f"{prefix}{key} must be one of {allowed}, got {cfg[group][name]!r}")
    renderer = cfg["renderer"]
    if (renderer["fov"] is None) == (renderer["focal_length"] is None):
        raise ModelConfigError(f"{prefix}renderer needs exactly one of fov and focal_length")
    _check_own_encoders(cfg, prefix)
    _check_pooled_stages(cfg, prefix)
    _check_symmetric_texture(cfg, prefix)
    _check_pose_ranges(cfg, prefix)
    _check_pose_vectors(cfg, prefix)
    _check_template_axes(cfg, prefix)
    _check_code_sizes(cfg, prefix)
    _check_generated_sizes(cfg, prefix)
    _check_neighbour_angle(cfg, prefix)
    _check_reconstruction_terms(cfg, prefix)
    _check_background_color(renderer)


def _settings(cfg: Mapping[str, Any]) -> Iterator[tuple[Any, str, Any, str]]:
    """Each setting of a configuration as ``(mapping, key, type hint, name)``: ``mapping[key]`` is its value (the
    configuration itself for ``image_size``, else its group; a group set to None has none)."""
    hints = typing.get_type_hints(UnicornConfig)
    for group in dataclasses.fields(UnicornConfig):
        schema = group.default_factory
        if not dataclasses.is_dataclass(schema):
            yield cfg, group.name, hints[group.name], group.name
        elif isinstance(cfg.get(group.name), Mapping):
            group_hints = typing.get_type_hints(schema)
            for f in dataclasses.fields(schema):
                yield cfg[group.name], f.name, group_hints[f.name], f"{group.name}.{f.name}"


def _check_switches(cfg: Mapping[str, Any], prefix: str) -> None:
    """The on / off settings (``bool`` fields) are True or False: a string ``"false"`` would read as on."""
    for values, key, hint, name in _settings(cfg):
        if hint is bool and not isinstance(values[key], bool):
            raise ModelConfigError(f"{prefix}{name} must be true or false, got {values[key]!r}")


def _whole_numbers_as_ints(cfg: dict[str, Any]) -> None:
    """The ``int`` settings given as whole floats (``64.0``) as ints, in place: the networks' constructors take
    ints."""
    for values, key, hint, _ in _settings(cfg):
        if hint is int and isinstance(values[key], float) and values[key].is_integer():
            values[key] = int(values[key])


def _finite_numbers(value: Any, n: int) -> bool:
    """``value`` is a sequence of ``n`` finite numbers (not bools)."""
    return (
        isinstance(value, Sequence)
        and not isinstance(value, str)
        and len(value) == n
        and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    )


def _listed(value: Any) -> Any:
    """A list of ``value``'s items where it is a sequence (a list, a tuple, an OmegaConf list), else ``value`` as it
    is, for the checks to name: a checkpoint's settings are not typed by the schema (None, a number)."""
    return list(value) if isinstance(value, Sequence) and not isinstance(value, str | bytes) else value


def _check_pose_ranges(cfg: Mapping[str, Any], prefix: str) -> None:
    """The candidates' angle ranges are ``(min, max)`` degrees with ``min <= max``; the azimuths' spans at most a
    turn (the anchors are spread over it: a wider range would put two candidates on one azimuth)."""
    for name in ("azim_range", "elev_range", "roll_range"):
        value = _listed(cfg["pose"][name])
        if not _finite_numbers(value, 2) or value[1] < value[0]:
            raise ModelConfigError(
                f"{prefix}pose.{name} must be two finite numbers [min, max] with min <= max, got {value}"
            )
    azim = _listed(cfg["pose"]["azim_range"])
    if azim[1] - azim[0] > 360:
        raise ModelConfigError(f"{prefix}pose.azim_range must span at most 360 degrees (one turn), got {azim}")


def _check_pose_vectors(cfg: Mapping[str, Any], prefix: str) -> None:
    """The translation and scale ranges and the prior translation as :class:`unicorn.model.pose.PoseHead` and
    :class:`unicorn.model.pose.ScaleHead` take them."""
    from unicorn.model.pose import scale_deviations, translation_ranges

    pose = cfg["pose"]
    try:
        translation_ranges(pose["T_range"], pose["prior_translation"])
        scale_deviations(pose["scale_range"])
    except ValueError as err:
        raise ModelConfigError(f"{prefix}pose.{err}") from None


def _check_template_axes(cfg: Mapping[str, Any], prefix: str) -> None:
    """The template's stretch is three positive numbers (:class:`unicorn.model.template.TemplateMesh`)."""
    axes = _listed(cfg["template"]["axes"])
    if not _finite_numbers(axes, 3) or min(axes) <= 0:
        raise ModelConfigError(f"{prefix}template.axes must be three finite numbers > 0 (x, y, z), got {axes}")


def _check_code_sizes(cfg: Mapping[str, Any], prefix: str) -> None:
    """Each code's active size is at most its size (:class:`unicorn.model.progressive.ProgressiveMask`)."""
    for branch in CODE_BRANCHES:
        group = cfg[branch]
        if group is not None and group["active_dims"] > group["code_dim"]:
            raise ModelConfigError(
                f"{prefix}{branch}.active_dims must be in [0, {branch}.code_dim={group['code_dim']}], "
                f"got {group['active_dims']}"
            )


def _check_generated_sizes(cfg: Mapping[str, Any], prefix: str) -> None:
    """The generators double their images from 1 x 1 (:class:`unicorn.model.generator.GiraffeGenerator`): the texture
    size, and with a background model the image size, are powers of 2."""
    sizes = {"texture.size": cfg["texture"]["size"]}
    if cfg["background"] is not None:
        sizes["image_size"] = cfg["image_size"]
    for key, size in sizes.items():
        if not (float(size).is_integer() and int(size) & (int(size) - 1) == 0):
            hint = " (the background model generates images of that size)" if key == "image_size" else ""
            raise ModelConfigError(f"{prefix}{key} must be a power of 2{hint}, got {size}")


def _check_neighbour_angle(cfg: Mapping[str, Any], prefix: str) -> None:
    """The neighbours' viewpoint bins span ``[loss.min_angle, 180]`` degrees: not empty
    (:class:`unicorn.objectives.neighbors.NeighborMemory`)."""
    if cfg["loss"]["min_angle"] >= 180:
        raise ModelConfigError(
            f"{prefix}loss.min_angle must be below 180 (the viewpoint bins span [min_angle, 180] degrees), "
            f"got {cfg['loss']['min_angle']}"
        )


def _check_reconstruction_terms(cfg: Mapping[str, Any], prefix: str) -> None:
    """The images are reconstructed by some term (:class:`unicorn.objectives.losses.ReconstructionLoss`): without
    one, nothing trains the pose or the shape and texture from the images."""
    loss = cfg["loss"]
    if loss["rgb_weight"] == 0 and (loss["perceptual"] is None or loss["perceptual_weight"] == 0):
        raise ModelConfigError(
            f"{prefix}loss.rgb_weight is 0 and there is no perceptual term (loss.perceptual={loss['perceptual']}, "
            f"perceptual_weight={loss['perceptual_weight']}): nothing would reconstruct the images"
        )


def _check_background_color(renderer: Mapping[str, Any]) -> None:
    """The renderer's background colour is RGB in [0, 1] (``renderer.background_color`` in the model's and in
    the training configuration alike)."""
    color = _listed(renderer["background_color"])
    if not _finite_numbers(color, 3) or not all(0 <= c <= 1 for c in color):
        raise ModelConfigError(f"renderer.background_color must be three numbers in [0, 1] (RGB), got {color}")


def _check_pooled_stages(cfg: Mapping[str, Any], prefix: str) -> None:
    """``encoder.pooled`` names distinct ResNet stages, at least one."""
    from unicorn.model.encoder import STAGES, distinct_stages

    pooled = _listed(cfg["encoder"]["pooled"])
    if not isinstance(pooled, list) or not all(isinstance(s, str) for s in pooled) or not distinct_stages(pooled):
        raise ModelConfigError(f"{prefix}encoder.pooled must name distinct stages of {list(STAGES)}, got {pooled}")


def _check_symmetric_texture(cfg: Mapping[str, Any], prefix: str) -> None:
    """A mirror-symmetric texture needs the seamless spherical UVs (mirrored by a horizontal flip of the map) and
    an even map width."""
    texture = cfg["texture"]
    if not texture["symmetric"]:
        return
    if (uv_mode := cfg["template"]["uv_mode"]) != "seamless":
        raise ModelConfigError(f"{prefix}texture.symmetric needs template.uv_mode='seamless', got {uv_mode!r}")
    if texture["size"] % 2:
        raise ModelConfigError(f"{prefix}texture.symmetric needs an even texture.size, got {texture['size']}")


def _check_own_encoders(cfg: Mapping[str, Any], prefix: str) -> None:
    """``encoder.own`` names distinct branches the model has, not all of them, and only with a shared encoder."""
    own = _listed(cfg["encoder"]["own"])
    if not isinstance(own, list) or not all(isinstance(b, str) for b in own):
        raise ModelConfigError(f"{prefix}encoder.own must be a list of branch names, got {own!r}")
    if not own:
        return
    branches = model_branches(cfg["background"] is not None)
    key = f"{prefix}encoder.own"
    if not cfg["encoder"]["shared"]:
        raise ModelConfigError(f"{key}={own} needs encoder.shared=true (without it every branch has its own encoder)")
    unknown = [b for b in own if b not in branches]
    if unknown:
        raise ModelConfigError(f"{key}: {unknown[0]!r} is not a branch of this model; branches: {list(branches)}")
    if len(set(own)) != len(own):
        raise ModelConfigError(f"{key} names a branch twice: {own}")
    if len(own) == len(branches):
        raise ModelConfigError(f"{key} gives every branch its own encoder; set encoder.shared=false instead")


def merge_config(config: Mapping[str, Any] | None = None, **overrides: Any) -> dict[str, Any]:
    """Full configuration: :data:`DEFAULT_CONFIG` updated group by group with ``config`` then ``overrides``; a
    size or count given as a whole float (``64.0``) is kept as an int.

    Raises:
        KeyError: an unknown group or key (typos fail loudly).
        ModelConfigError: a value out of range or not among the allowed ones (:func:`check_model_config`).
    """
    merged = copy.deepcopy(DEFAULT_CONFIG)
    for source in (config or {}, overrides):
        for group, value in source.items():
            if group not in merged:
                raise KeyError(f"unknown model config group {group!r}; known: {sorted(merged)}")
            if value is None:
                if group != "background":
                    raise KeyError(f"only the background model can be disabled (None), not {group!r}")
                merged[group] = None
            elif group == "image_size":
                # numpy's integers as Python's; any other value as given, for the checks to name (64.5 is not 64)
                merged[group] = int(value) if isinstance(value, Integral) and not isinstance(value, bool) else value
            else:
                if not isinstance(value, Mapping):  # dict(3) would say only that an int is not iterable
                    raise ModelConfigError(f"model config group {group!r} must be a mapping of its keys, got {value!r}")
                base = merged[group] if merged[group] is not None else copy.deepcopy(DEFAULT_CONFIG[group])
                for key, v in value.items():
                    if key not in base:
                        raise KeyError(f"unknown key {key!r} in model config group {group!r}; known: {sorted(base)}")
                    base[key] = dict(v) if isinstance(v, Mapping) else v
                merged[group] = base
    check_model_config(merged)
    _whole_numbers_as_ints(merged)
    return merged
