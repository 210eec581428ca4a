"""Load the released UNICORN checkpoints (``model.pkl``, ``car_big.pkl``, ...) into :class:`Unicorn`.

A released checkpoint is a ``torch.save``d dict with ``epoch``, ``model_kwargs`` (the YAML ``model``
section), ``model_state`` and optimizer / scheduler states. Its parameter names map onto ours as follows
(``N`` = the reference's MLP layer indices 0, 2, 4, 6, kept unchanged):

=====================================================  ====================================================
reference                                              unicorn
=====================================================  ====================================================
``encoder.encoder.{0,1,4,5,6,7}.*`` (small)            ``encoders.0.{conv1,bn1,layer1..layer4}.*``
``encoder_{sh,tx,pose,bg}.encoder.*`` (big)            ``encoders.{0,1,2,3}.*``
``deform_field.regressor.N.*``                         ``shape.regressor.N.*``
``deform_field.field.{linear_x,linear_z,mlp.N}.*``     ``shape.field.{linear_x,linear_z,mlp.N}.*``
``txt_generator.regressor.N.*``                        ``texture.regressor.N.*``
``txt_generator.generator.{conv_layers,conv_rgb}.i.*`` ``texture.generator.{conv_layers,conv_rgb}.i.*``
``bkg_generator.*``                                    ``background.*`` (same sub-names)
``rot_regressors.k.N.*``                               ``pose.rot_regressors.k.N.*``, last layer's rows
                                                       permuted ``[1, 0, 2]`` (the reference's channel swap)
``T_regressors.k.N.*``                                 ``pose.T_regressors.k.N.*``
``proba_regressor.N.*``                                ``pose.proba_regressor.N.*``
``scale_regressor.N.*``                                ``scale.regressor.N.*``
``perceptual_loss.slice{1..5}.i.*``                    VGG16 ``features.i.*`` (returned separately)
=====================================================  ====================================================

Dropped: buffers derived from the configuration (``uvs``, ``R_init``, ``R_range``, ``T_init``, ``T_range``,
``scale_init``, ``scale_range``, the blur ``*.upsample_rgb.1.kernel``, and ``T_cam`` / ``R_cam``, the camera buffers
of the older reference versions the small released models come from). The ``module.`` prefix of a model saved from
the reference's multi-GPU training is removed, as the reference's loader does. To reproduce the released models'
images the model is built with ``template.uv_mode = "reference"`` (per-vertex UVs, ``align_corners=True``,
border padding) and ``renderer.composite = "reference"`` (``rgb * A + (1 - A) * bkg`` over a white render).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from typing import Any

import torch

from unicorn.checks import SizeLimitError, is_number, is_whole
from unicorn.config.presets import model_preset
from unicorn.io.serialization import CheckpointError, kind_of, load_checkpoint_file, model_device
from unicorn.model.autoencoder import Unicorn
from unicorn.model.config import merge_config
from unicorn.model.progressive import active_dims_at
from unicorn.objectives.perceptual import VGGPerceptualLoss

__all__ = [
    "ReferenceCheckpointError",
    "config_from_reference",
    "convert_reference_state_dict",
    "load_reference_checkpoint",
    "reference_model",
]


class ReferenceCheckpointError(CheckpointError, KeyError):
    """A released checkpoint whose keys do not fit the model it describes (also a ``KeyError``: a key problem)."""

    __str__ = Exception.__str__  # the message as written, not KeyError's quoted repr


_RESNET_CHILDREN = {"0": "conv1", "1": "bn1", "4": "layer1", "5": "layer2", "6": "layer3", "7": "layer4"}
_ENCODER_INDEX = {"encoder": 0, "encoder_sh": 0, "encoder_tx": 1, "encoder_pose": 2, "encoder_bg": 3}
# the configuration's buffers; T_cam (the prior translation, kept apart from a zero T_init there) and R_cam (the
# identity) are those of the older reference versions the small released models were saved with
_DROPPED = re.compile(r"^(uvs|R_init|R_range|T_init|T_range|T_cam|R_cam|scale_init|scale_range)$|\.kernel$|^renderer\.")
_PREFIXES = {
    "deform_field.": "shape.",
    "txt_generator.": "texture.",
    "bkg_generator.": "background.",
    "rot_regressors.": "pose.rot_regressors.",
    "T_regressors.": "pose.T_regressors.",
    "proba_regressor.": "pose.proba_regressor.",
    "scale_regressor.": "scale.regressor.",
}
_ROT_SWAP = [1, 0, 2]


def _state_dict_of(checkpoint: Mapping[str, Any]) -> Mapping[str, torch.Tensor]:
    """The reference state dict of a checkpoint dict (or the bare state dict itself), checked to hold tensors
    under names; the ``module.`` prefix of a model saved from the reference's multi-GPU training
    (``DistributedDataParallel``), which the reference's loader strips too, is removed.

    Raises:
        CheckpointError: ``model_state`` is not a dict of tensors under string names (the message names the first
            other key or value), or a dict without ``model_state`` is no state dict either (its keys named).
    """
    if "model_state" not in checkpoint and not all(isinstance(v, torch.Tensor) for v in checkpoint.values()):
        # another program's checkpoint (a Lightning .ckpt without hyper-parameters...), not a bare state dict
        keys = sorted(map(str, checkpoint))[:10]
        raise CheckpointError(f"no 'model_state' and not a state dict (keys {keys}): not a released UNICORN checkpoint")
    state = checkpoint["model_state"] if "model_state" in checkpoint else checkpoint
    if not isinstance(state, Mapping):
        raise CheckpointError(f"model_state is {kind_of(state)}, not a dict of tensors")
    key = next((k for k in state if not isinstance(k, str)), None)
    if key is not None:
        raise CheckpointError(f"model_state has the key {key!r} ({kind_of(key)}), not a parameter name")
    other = next((k for k, v in state.items() if not isinstance(v, torch.Tensor)), None)
    if other is not None:
        raise CheckpointError(f"model_state[{other!r}] is {kind_of(state[other])}, not a tensor")
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module.") :]: v for k, v in state.items()}
    return state


def _weight(state: Mapping[str, torch.Tensor], key: str) -> torch.Tensor:
    """``state[key]``, a layer's weight (its first dimension is the layer's width).

    Raises:
        ReferenceCheckpointError: the key is missing, or the tensor has no dimension.
    """
    if key not in state:
        raise ReferenceCheckpointError(f"missing key {key!r}: the checkpoint lacks this tensor of its model")
    if state[key].ndim == 0:
        raise ReferenceCheckpointError(f"model_state[{key!r}] is a scalar, not a layer's weight")
    return state[key]


def _last_linear_index(state: Mapping[str, torch.Tensor], prefix: str) -> int:
    """The index of the last layer of the MLP under ``prefix`` (``<prefix><i>.weight`` and ``.bias``).

    Raises:
        ReferenceCheckpointError: no layer, or a layer with its bias but not its weight, or the other way round
            (the missing key is named: the layer count is read from the keys).
    """
    found: dict[int, set[str]] = {}
    for key in state:
        if m := re.match(re.escape(prefix) + r"(\d+)\.(weight|bias)$", key):
            found.setdefault(int(m.group(1)), set()).add(m.group(2))
    if not found:
        raise ReferenceCheckpointError(f"no MLP layers under '{prefix}'")
    for index, names in sorted(found.items()):
        for name in {"weight", "bias"} - names:
            raise ReferenceCheckpointError(f"missing key '{prefix}{index}.{name}': the checkpoint lacks this tensor")
    return max(found)


def convert_reference_state_dict(
    state: Mapping[str, torch.Tensor], strict: bool = True
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Rename a reference ``model_state`` into ours.

    Args:
        state: the reference state dict (or a checkpoint dict holding it under ``model_state``).
        strict: raise on keys that are neither mapped nor known to be droppable.

    Returns:
        ``(model_state, vgg_state)``: our state dict (without the mask / switch buffers, which come from
        the configuration) and the VGG16 perceptual weights under torchvision names (empty if absent).

    Raises:
        ReferenceCheckpointError: unknown keys (``strict``).
    """
    state = _state_dict_of(state)
    ours: dict[str, torch.Tensor] = {}
    vgg: dict[str, torch.Tensor] = {}
    unknown: list[str] = []
    rot_last = {
        m.group(1): _last_linear_index(state, f"rot_regressors.{m.group(1)}.")
        for k in state
        if (m := re.match(r"rot_regressors\.(\d+)\.", k))
    }
    for key, value in state.items():
        if m := re.match(r"^(encoder(?:_sh|_tx|_pose|_bg)?)\.(?:encoder\.)?(\d+)\.(.+)$", key):
            child = _RESNET_CHILDREN.get(m.group(2))
            if child is None:
                unknown.append(key)
                continue
            ours[f"encoders.{_ENCODER_INDEX[m.group(1)]}.{child}.{m.group(3)}"] = value
        elif m := re.match(r"^perceptual_loss\.slice\d+\.(\d+)\.(weight|bias)$", key):
            vgg[f"features.{m.group(1)}.{m.group(2)}"] = value
        elif key.startswith("perceptual_loss.") or _DROPPED.search(key):
            continue
        else:
            prefix = next((p for p in _PREFIXES if key.startswith(p)), None)
            if prefix is None:
                unknown.append(key)
                continue
            new_key = _PREFIXES[prefix] + key[len(prefix) :]
            if m := re.match(r"^rot_regressors\.(\d+)\.(\d+)\.(weight|bias)$", key):
                # a last layer of another size is left as it is: the weights' fit check names it
                if int(m.group(2)) == rot_last[m.group(1)] and value.shape[:1] == (len(_ROT_SWAP),):
                    # the reference reads its rotation head as tanh(out)[..., [1, 0, 2]] -> (azim, elev, roll)
                    value = value[_ROT_SWAP]
            ours[new_key] = value
    if unknown and strict:
        raise ReferenceCheckpointError(
            f"unrecognised keys in the reference checkpoint ({len(unknown)}): {unknown[:10]}"
        )
    return ours, vgg


def _model_kwargs(checkpoint: Mapping[str, Any]) -> Mapping[str, Any]:
    """A released checkpoint's ``model_kwargs`` (empty for a bare state dict or when absent).

    Raises:
        CheckpointError: ``model_kwargs`` is not a dict.
    """
    return _section(checkpoint, "model_kwargs") if "model_state" in checkpoint else {}


def _section(mapping: Mapping[str, Any], *keys: str) -> Mapping[str, Any]:
    """The dict at ``mapping[keys[0]][keys[1]]...`` of a checkpoint; empty when a key is absent or None.

    Raises:
        CheckpointError: a value on the way is not a dict (the message names it).
    """
    for i, key in enumerate(keys):
        value = mapping.get(key)
        if value is None:
            return {}
        if not isinstance(value, Mapping):
            raise CheckpointError(f"{_field_name(keys[: i + 1])} is {kind_of(value)}, not a dict")
        mapping = value
    return mapping


def _field_name(keys: tuple[str, ...]) -> str:
    """``("model_kwargs", "mesh")`` -> ``model_kwargs['mesh']`` (sections under ``model_kwargs``)."""
    keys = keys if keys[0] == "model_kwargs" else ("model_kwargs", *keys)
    return keys[0] + "".join(f"[{k!r}]" for k in keys[1:])


def _number(value: Any, *keys: str) -> float:
    """``value``, the field ``model_kwargs[keys...]``, as a float.

    Raises:
        CheckpointError: not a finite number.
    """
    if not is_number(value):
        raise CheckpointError(f"{_field_name(keys)} = {value!r} is not a finite number")
    return float(value)


def _numbers(value: Any, *keys: str) -> list[float]:
    """``value``, the field ``model_kwargs[keys...]``, as a list of floats.

    Raises:
        CheckpointError: not a list of finite numbers.
    """
    if not isinstance(value, list | tuple):
        raise CheckpointError(f"{_field_name(keys)} = {value!r} is not a list of numbers")
    return [_number(v, *keys) for v in value]


def _epoch(checkpoint: Mapping[str, Any]) -> int | None:
    """The saved ``epoch`` of a released checkpoint (None for a bare state dict or when absent).

    Raises:
        CheckpointError: not a whole number.
    """
    epoch = checkpoint.get("epoch") if "model_state" in checkpoint else None
    if epoch is not None and not (is_whole(epoch) and epoch >= 0):
        raise CheckpointError(f"epoch = {epoch!r} is not a whole number >= 0")
    return epoch


def config_from_reference(checkpoint: Mapping[str, Any], **overrides: Any) -> dict[str, Any]:
    """Our model configuration for a released checkpoint.

    Sizes (shared or separate encoders, code sizes, field and generator widths, number of candidates) come
    from the tensor shapes; ranges, mesh scale, camera and progressive state from ``model_kwargs`` and
    ``epoch`` when present, else from the dataset family's defaults (ShapeNet when there is no background
    generator). UVs and compositing follow the reference; losses are off (``perceptual=None``) unless
    overridden.
    """
    state = _state_dict_of(checkpoint)
    kwargs = _model_kwargs(checkpoint)
    has_bg = any(k.startswith("bkg_generator.") for k in state)
    shared = not any(k.startswith("encoder_sh.") for k in state)
    cfg = model_preset("real" if has_bg else "shapenet", "small" if shared else "big")
    cfg["encoder"]["shared"] = shared
    n_cand = _sizes_from_state(cfg, state)
    _pose_from_kwargs(cfg, kwargs, n_cand)
    _template_from_kwargs(cfg, kwargs)
    if "img_size" in kwargs:
        size = kwargs["img_size"]
        size = size[0] if isinstance(size, list | tuple) and size else size  # (height, width): square images
        cfg["image_size"] = int(_number(size, "img_size"))
    _renderer_from_kwargs(cfg, kwargs)
    cfg["loss"]["perceptual"] = None
    _progressive_from_kwargs(cfg, kwargs, _epoch(checkpoint))
    return merge_config(cfg, **overrides)


def _sizes_from_state(cfg: dict[str, Any], state: Mapping[str, torch.Tensor]) -> int:
    """Set the networks' sizes in ``cfg`` from the reference's tensor shapes; returns the number of pose
    candidates."""

    def out_dim(prefix: str) -> int:
        return _weight(state, f"{prefix}{_last_linear_index(state, prefix)}.weight").shape[0]

    def n_hidden(prefix: str) -> int:
        return _last_linear_index(state, prefix) // 2

    def units(prefix: str) -> int:
        return _weight(state, f"{prefix}0.weight").shape[0]

    cfg["shape"].update(
        code_dim=out_dim("deform_field.regressor."),
        n_reg_units=units("deform_field.regressor."),
        n_reg_layers=n_hidden("deform_field.regressor."),
        n_field_units=_weight(state, "deform_field.field.linear_x.weight").shape[0],
        n_field_layers=n_hidden("deform_field.field.mlp."),
    )
    for group, prefix in (("texture", "txt_generator."), ("background", "bkg_generator.")):
        if cfg[group] is None:
            continue
        convs = [state[k] for k in state if re.match(re.escape(prefix) + r"generator\.conv_layers\.\d+\.weight$", k)]
        if not convs or min(w.ndim for w in convs) == 0:
            _weight(state, f"{prefix}generator.conv_layers.0.weight")  # says what is missing
        cfg[group].update(
            code_dim=out_dim(f"{prefix}regressor."),
            n_reg_units=units(f"{prefix}regressor."),
            n_reg_layers=n_hidden(f"{prefix}regressor."),
            min_features=min(w.shape[0] for w in convs),
        )
        if group == "texture":
            cfg[group]["size"] = 2 ** len(convs)
    cfg["pose"].update(n_units=units("T_regressors.0."), n_layers=n_hidden("T_regressors.0."))
    bg_convs = [k for k in state if re.match(r"bkg_generator\.generator\.conv_layers\.\d+\.weight$", k)]
    if bg_convs:  # the background generator's output is the image
        cfg["image_size"] = 2 ** len(bg_convs)
    return len({k.split(".")[1] for k in state if k.startswith("rot_regressors.")})


def _pose_from_kwargs(cfg: dict[str, Any], kwargs: Mapping[str, Any], n_cand: int) -> None:
    """The pose candidates' grid and the ranges of the saved ``rend_predictor`` section."""
    rp = _section(kwargs, "rend_predictor")
    grid = rp.get("n_elev_azim", (1, n_cand))
    if not (isinstance(grid, list | tuple) and len(grid) == 2 and all(is_whole(v) for v in grid)):
        raise CheckpointError(f"model_kwargs['rend_predictor']['n_elev_azim'] = {grid!r} is not two whole numbers")
    n_elev, n_azim = grid
    cfg["pose"].update(n_elev=int(n_elev), n_azim=int(n_azim))
    for key in ("azim_range", "elev_range", "roll_range", "T_range", "scale_range", "prior_translation"):
        if key in rp:
            cfg["pose"][key] = rp[key]
    if int(n_elev) * int(n_azim) != n_cand:
        raise CheckpointError(f"checkpoint has {n_cand} pose candidates but n_elev_azim = {rp.get('n_elev_azim')}")


def _template_from_kwargs(cfg: dict[str, Any], kwargs: Mapping[str, Any]) -> None:
    """The template mesh of the saved ``mesh`` section, with the reference's per-vertex UVs."""
    mesh = _section(kwargs, "mesh")
    if "scale" in mesh:
        cfg["template"]["scale"] = _number(mesh["scale"], "mesh", "scale")
    init = mesh.get("init", "ellipse")  # what every released model's config says
    if not isinstance(init, str) or not ("ellipse" in init or "sphere" in init):
        raise CheckpointError(f"model_kwargs['mesh']['init'] = {init!r} is not a template ('ellipse' or 'sphere')")
    cfg["template"]["axes"] = (1.0, 0.7, 0.7) if "ellipse" in init else (1.0, 1.0, 1.0)
    cfg["template"]["level"] = 4 if "hr" in init else 3
    cfg["template"]["bottom"] = 1.0  # the reference's templates are whole ellipsoids and spheres
    cfg["template"]["uv_mode"] = "reference"


def _renderer_from_kwargs(cfg: dict[str, Any], kwargs: Mapping[str, Any]) -> None:
    """Camera, blur and background colour of the saved ``renderer`` section, with the reference's compositing."""
    rd = _section(kwargs, "renderer")
    cams = _section(kwargs, "renderer", "cameras")
    name = cams.get("name", "fov" if cams else None)
    if name == "perspective":
        if "focal_length" not in cams:
            raise CheckpointError("model_kwargs['renderer']['cameras'] is a perspective camera without focal_length")
        cfg["renderer"].update(
            fov=None, focal_length=_number(cams["focal_length"], "renderer", "cameras", "focal_length")
        )
    elif name == "fov":
        cfg["renderer"].update(fov=_number(cams.get("fov", 30.0), "renderer", "cameras", "fov"), focal_length=None)
    elif name is not None:
        raise CheckpointError(
            f"model_kwargs['renderer']['cameras']['name'] = {name!r} is not a camera of the reference ('fov' or "
            "'perspective')"
        )
    options = dict(cfg["renderer"]["options"])
    if "sigma" in rd:
        options["sigma"] = _number(rd["sigma"], "renderer", "sigma")
    if "faces_per_pixel" in rd:
        k = rd["faces_per_pixel"]
        if not (is_whole(k) and k > 0):
            raise CheckpointError(f"model_kwargs['renderer']['faces_per_pixel'] = {k!r} is not a whole number > 0")
        options["faces_per_pixel"] = rd["faces_per_pixel"]
    cfg["renderer"].update(options=options, composite="reference")
    if rd.get("background_color") is not None:
        cfg["renderer"]["background_color"] = tuple(_numbers(rd["background_color"], "renderer", "background_color"))


def _progressive_from_kwargs(cfg: dict[str, Any], kwargs: Mapping[str, Any], epoch: int | None) -> None:
    """The code dimensions active at the saved epoch (fully conditioned when unknown)."""
    for group, keys in (
        ("shape", ("mesh", "deform_fields")),
        ("texture", ("mesh", "texture_uv")),
        ("background", ("background",)),
    ):
        if cfg[group] is None:
            continue
        section = _section(kwargs, *keys)
        powers, milestones = section.get("powers"), section.get("milestones")
        # present, they are lists of numbers (absent: the code fully conditioned)
        powers = None if powers is None else _numbers(powers, *keys, "powers")
        milestones = None if milestones is None else _numbers(milestones, *keys, "milestones")
        if epoch is not None and powers and milestones and len(powers) == len(milestones):
            cfg[group]["active_dims"] = min(active_dims_at(epoch, powers, milestones), cfg[group]["code_dim"])
        else:
            cfg[group]["active_dims"] = cfg[group]["code_dim"]


def _stage_switches(checkpoint: Mapping[str, Any]) -> dict[str, bool]:
    """Stage-1 switches at the saved epoch: a milestone m is live (output held off) while epoch < m."""
    epoch = _epoch(checkpoint)
    milestones = _section(_model_kwargs(checkpoint), "milestones")
    switches = {}
    for name, key in (
        ("translation", "freeze_T_predictor"),
        ("deformation", "freeze_shape"),
        ("scale", "freeze_scale_predictor"),
    ):
        m = milestones.get(key, 0)
        if not isinstance(m, bool):
            m = _number(m, "milestones", key)
        live = bool(m) if isinstance(m, bool) else (epoch is not None and epoch < m)
        switches[name] = not live
    return switches


def load_reference_checkpoint(
    checkpoint: str | os.PathLike | Mapping[str, Any],
    strict: bool = True,
    with_perceptual: bool = False,
    map_location: str | torch.device = "cpu",
    trust: bool = False,
    **overrides: Any,
) -> Unicorn:
    """Build a :class:`Unicorn` from a released UNICORN checkpoint and load its weights.

    Args:
        checkpoint: path of the ``.pkl`` file, or the loaded dict (or a bare reference state dict).
        strict: fail on unrecognised reference keys or on our parameters left unset.
        with_perceptual: also build the VGG16 perceptual loss from the weights stored in the checkpoint.
        map_location: where to load the tensors; the model is returned on that device (when it names one:
            ``torch.load``'s remapping dicts and functions leave the model on the CPU).
        trust: read the file with full unpickling, for files from a source you trust (it can run arbitrary
            code); by default only tensors and plain data are read, which is all the released files hold.
        overrides: configuration groups overriding the inferred ones (see :func:`config_from_reference`).

    Returns:
        the model in eval mode.

    Raises:
        unicorn.io.serialization.UnsafeCheckpointError: the file needs full unpickling and ``trust`` is False.
        unicorn.io.serialization.CheckpointError: a value of the checkpoint of the wrong type (the message names
            it, and the file when given a path), or a file of another format (a ``unicorn-train`` checkpoint or a
            :func:`~unicorn.io.save_model` file, which :func:`~unicorn.io.load_model` reads); given a path, NaN,
            infinite or negative-variance weights (:func:`~unicorn.io.checkpoints.check_weight_values`).
        unicorn.io.checkpoints.ModelTooLargeError: a model, image or texture size above the limits.
        ReferenceCheckpointError: keys that do not fit the model (``strict``), weights of other shapes, or
            ``with_perceptual`` on a file without the VGG weights (the message names the file when given a path).
        unicorn.io.serialization.MapLocationError: ``map_location`` is not a device of this machine, checked before
            the file is read.
        ValueError: ``map_location`` is the meta device.
    """
    device = model_device(map_location)
    if isinstance(checkpoint, Mapping):
        model = reference_model(checkpoint, "the released checkpoint", strict, with_perceptual, **overrides)
        return model if device is None else model.to(device)
    from unicorn.io.checkpoints import check_weight_values, checkpoint_format  # which imports this module

    path = checkpoint
    # the released files pickle plain dicts and tensors (the optimizer state needs no custom classes)
    checkpoint = load_checkpoint_file(path, map_location=map_location, trust=trust)
    if not isinstance(checkpoint, Mapping):
        raise CheckpointError(f"{path} holds {kind_of(checkpoint)}, not a released UNICORN checkpoint (a dict)")
    other = {"lightning": "a unicorn-train checkpoint", "plain": "a unicorn.io.save_model file"}
    kind = other.get(checkpoint_format(checkpoint) or "")
    if kind:
        raise CheckpointError(
            f"{path} is {kind}, not a released UNICORN checkpoint: load it with unicorn.io.load_model"
        )
    source = f"released checkpoint {path}"
    try:
        model = reference_model(checkpoint, source, strict, with_perceptual, **overrides)
    except CheckpointError as err:
        if isinstance(err, SizeLimitError):
            raise  # names the file already
        raise type(err)(f"{source}: {err}") from None
    check_weight_values(model, path)  # as load_model: NaN weights would give NaN meshes without a word
    return model if device is None else model.to(device)  # built on the CPU, whatever device the tensors came to


def reference_model(
    checkpoint: Mapping[str, Any], source: str, strict: bool = True, with_perceptual: bool = False, **overrides: Any
) -> Unicorn:
    """:func:`load_reference_checkpoint` of a loaded checkpoint dict; ``source`` names it in the size errors
    (``"released checkpoint PATH"``).

    Raises:
        as :func:`load_reference_checkpoint`.
    """
    from unicorn.io.checkpoints import check_stored_config, weights_misfit  # which imports this module

    state, vgg = convert_reference_state_dict(checkpoint, strict=strict)
    cfg = config_from_reference(checkpoint, **overrides)
    check_stored_config(cfg, source)  # before anything is allocated
    model = Unicorn(cfg)
    if with_perceptual:
        if not vgg:
            raise ReferenceCheckpointError(
                "the checkpoint holds no perceptual_loss weights (load it without with_perceptual)"
            )
        model.perceptual = VGGPerceptualLoss(vgg).to(next(model.parameters()).device)
        model.config["loss"]["perceptual"] = "vgg"
    # buffers that come from the configuration, not from the reference, and the VGG weights loaded above
    derived = re.compile(r"(\.mask\.active|use_translation|use_deformation|use_scale|^renderer\.|^perceptual\.)")
    own = {k: v for k, v in model.state_dict().items() if not derived.search(k)}
    misfit = weights_misfit(state, own, strict)
    if misfit:
        raise ReferenceCheckpointError(f"checkpoint does not fit the model: {misfit}")
    model.load_state_dict(state, strict=False)  # every weight checked above
    model.set_stage_switches(**_stage_switches(checkpoint))
    return model.eval()
