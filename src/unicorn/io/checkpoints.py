"""Load a :class:`~unicorn.model.Unicorn` from any checkpoint file the project meets, with one function.

Three formats are recognised by their keys:

- **released UNICORN** ``.pkl`` (``model_state`` and ``model_kwargs``): converted by
  :func:`unicorn.io.reference_checkpoints.load_reference_checkpoint`;
- **Lightning** ``.ckpt`` written by ``unicorn-train`` (``state_dict`` and ``hyper_parameters``): the model is built
  from ``hyper_parameters["model"]`` (the :class:`~unicorn.lit.UnicornLitModule`'s ``model`` argument) and the
  ``model.``-prefixed weights are loaded; the module's ``texture_average_p`` buffer tells whether the network was
  still in its mean-texture phase;
- **plain** files of :func:`save_model` (``{"format": "unicorn-model", "config", "state_dict", "info"}``), small
  and independent of Lightning.

The perceptual loss is never rebuilt (it is not needed to predict and its VGG weights may not be on this machine).

Checkpoints are pickles, and a pickle can run any code while it is read. Every file is therefore read with
PyTorch's restricted unpickler (tensors and plain data only, see :mod:`unicorn.io.serialization`); one that needs
more is refused with :class:`~unicorn.io.serialization.UnsafeCheckpointError` unless ``trust=True`` is passed (the
command-line tools' ``--trust-checkpoint``): do that only for files from a source you trust. Files written by
unicorn carry a content hash that is checked on load.
"""

from __future__ import annotations

import copy
import dataclasses
import numbers
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from unicorn.checks import SizeLimitError, is_number
from unicorn.data.images import check_image_size
from unicorn.io.reference_checkpoints import reference_model
from unicorn.io.run_folder import run_dataset, run_of_checkpoint
from unicorn.io.serialization import (
    CheckpointError,
    CorruptCheckpointError,
    MapLocationError,
    UnsafeCheckpointError,
    atomic_save,
    kind_of,
    load_checkpoint_file,
    model_device,
)
from unicorn.model import MAX_MODEL_PARAMS, Unicorn, merge_config
from unicorn.model import check_model_size as _check_model_size
from unicorn.model.config import DEFAULT_CONFIG
from unicorn.registry import PLUGINS_ENV, UnknownNameError

__all__ = [
    "MAX_MODEL_PARAMS",
    "CheckpointError",
    "CheckpointInfo",
    "CorruptCheckpointError",
    "MapLocationError",
    "ModelTooLargeError",
    "NotATrainingCheckpointError",
    "UnsafeCheckpointError",
    "check_model_size",
    "check_stored_config",
    "check_weight_values",
    "check_weights_fit",
    "checkpoint_format",
    "check_training_checkpoint",
    "init_weights",
    "load_model",
    "read_checkpoint",
    "save_model",
    "weights_misfit",
]

PLAIN_FORMAT = "unicorn-model"
Format = Literal["reference", "lightning", "plain"]

#: what a training run's checkpoint holds beside the weights (written by Lightning)
_TRAINING_KEY = "pytorch-lightning_version"


class ModelTooLargeError(CheckpointError, SizeLimitError):
    """A checkpoint's stored configuration describes a model above the size limit."""


class NotATrainingCheckpointError(CheckpointError):
    """A file that holds weights but no training state was given to resume training."""


def checkpoint_format(data: Mapping[str, Any]) -> Format | None:
    """The format of a loaded checkpoint dict (see the module docstring), or None for none of them."""
    if "model_state" in data:
        return "reference"
    if "state_dict" in data and "hyper_parameters" in data:
        return "lightning"
    if data.get("format") == PLAIN_FORMAT:
        return "plain"
    return None


def check_training_checkpoint(data: Mapping[str, Any], path: str | os.PathLike) -> None:
    """Check that a loaded checkpoint is one ``unicorn-train`` can resume (``ckpt_path``).

    Raises:
        NotATrainingCheckpointError: a released model, a :func:`save_model` file or another dict; the message
            says to start from its weights with ``init_from``.
    """
    if _TRAINING_KEY in data:
        return
    kind = {
        "reference": "a released UNICORN model",
        "plain": "a unicorn.io.save_model file",
        "lightning": "a Lightning checkpoint without training state",
    }.get(checkpoint_format(data) or "", "not a unicorn-train checkpoint")
    raise NotATrainingCheckpointError(
        f"ckpt_path: {path} is {kind}; ckpt_path resumes a unicorn-train run (a .ckpt with its optimizer and "
        f"iteration); to start training from these weights use init_from={path} instead"
    )


def check_model_size(
    config: Mapping[str, Any], setting: str, limit: int | None = None, error: type[SizeLimitError] = ModelTooLargeError
) -> None:
    """:func:`unicorn.model.check_model_size`, raising :class:`ModelTooLargeError` for a checkpoint by default."""
    _check_model_size(config, setting, limit, error)


def check_stored_config(config: Mapping[str, Any], setting: str) -> None:
    """Refuse a merged model config read from a checkpoint whose sizes are above the limits, before anything is
    built: its input image and texture map as training bounds ``dataset.img_size`` and ``model.texture.size``
    (:func:`unicorn.data.images.check_image_size`), its networks as :func:`check_model_size`.

    Args:
        config: the merged model config.
        setting: what asks for the model, named in the message (``"checkpoint PATH"``).

    Raises:
        ModelTooLargeError: the first size above its limit (the message names the key and the limit).
    """
    for key, what, side in (
        ("image_size", "an input image", config["image_size"]),
        ("texture.size", "a texture map", config["texture"]["size"]),
    ):
        try:
            check_image_size(f"{setting}: {key}={side}", what, side)
        except SizeLimitError as err:
            raise ModelTooLargeError(str(err)) from None
    check_model_size(config, setting)


@dataclass
class CheckpointInfo:
    """What is known about a loaded checkpoint besides the weights.

    Attributes:
        path: the file.
        format: ``"reference"``, ``"lightning"`` or ``"plain"``.
        epoch: saved epoch, when stored.
        step: saved iteration (Lightning ``global_step``), when stored.
        average_texture: the model was trained with mean-colour textures at that point (predict with
            ``average_texture=True`` to see what it was optimised for).
        run_dir: the training run folder (``<run>/checkpoints/x.ckpt`` -> ``<run>``), when the file sits in one.
        dataset: the training run's ``dataset`` config (``name``, ``root``, ``categories``...), when found in
            ``<run>/config.yaml``.
        extra: other format-specific fields (e.g. Lightning's ``stage``).
    """

    path: Path
    format: Format
    epoch: int | None = None
    step: int | None = None
    average_texture: bool = False
    run_dir: Path | None = None
    dataset: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        """One line for logs: format, file, epoch / step."""
        parts = [f"{self.format} checkpoint {self.path}"]
        if self.epoch is not None:
            parts.append(f"epoch {self.epoch}")
        if self.step is not None:
            parts.append(f"step {self.step}")
        return ", ".join(parts)


def read_checkpoint(
    path: str | os.PathLike, map_location: str | torch.device = "cpu", trust: bool = False
) -> dict[str, Any]:
    """Load a checkpoint dict without running code from it, and check its content hash when it has one.

    Args:
        path: the file.
        map_location: where tensors are loaded.
        trust: allow full unpickling, for files from a source you trust (it can run arbitrary code).

    Raises:
        FileNotFoundError: no such file.
        UnsafeCheckpointError: the file needs full unpickling and ``trust`` is False.
        CorruptCheckpointError: the content does not match its stored hash.
        CheckpointError: not a readable torch file or not a dict.
    """
    path = Path(path).expanduser()
    data = load_checkpoint_file(path, map_location=map_location, trust=trust)
    if not isinstance(data, Mapping):
        raise CheckpointError(f"checkpoint {path} holds a {type(data).__name__}, not a dict")
    return dict(data)


def _to_plain(value: Any) -> Any:
    """OmegaConf containers (and anything nested) to plain dicts / lists."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(value, DictConfig | ListConfig):
            return OmegaConf.to_container(value, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    if isinstance(value, Mapping):
        return {k: _to_plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(_to_plain(v) for v in value)
    return value


def _stored_model(stored: Any, path: Path, field: str, overrides: Mapping[str, Any] | None) -> Unicorn:
    """The model of the config a checkpoint stores under ``field``, built once that config is checked (a dict of
    the groups and keys this version knows, sizes within :func:`check_stored_config`), with the perceptual loss
    off and the caller's group overrides merged in.

    Raises:
        CheckpointError: a config that is not a dict of groups, or with groups or keys this version does not know.
        ModelTooLargeError: sizes above the limits.
    """
    config = _to_plain(stored)
    if not isinstance(config, Mapping):
        raise CheckpointError(f"checkpoint {path}: its {field} is {kind_of(config)}, not a model config (a dict)")
    for group, value in config.items():
        if group not in DEFAULT_CONFIG:
            continue  # merge_config names it
        if group == "image_size":
            fits = is_number(value)
        else:
            fits = value is None or isinstance(value, Mapping)
        if not fits:
            expected = "a number" if group == "image_size" else "a dict"
            raise CheckpointError(f"checkpoint {path}: its {field}[{group!r}] is {kind_of(value)}, not {expected}")
    try:
        cfg = merge_config(config)
    except KeyError as err:  # a group or key of another version
        raise CheckpointError(
            f"checkpoint {path}: its model settings are not ones this version of unicorn knows ({err.args[0]}); "
            "the file may come from another version of unicorn"
        ) from None
    cfg["loss"]["perceptual"] = None
    for group, value in (overrides or {}).items():
        if isinstance(value, Mapping) and isinstance(cfg.get(group), Mapping):
            cfg[group] = {**cfg[group], **dict(value)}
        else:
            cfg[group] = value
    cfg = merge_config(cfg)
    check_stored_config(cfg, f"checkpoint {path}")
    try:
        return Unicorn(cfg)
    except UnknownNameError as err:  # e.g. a renderer a plugin registered where the checkpoint was made
        raise CheckpointError(
            f"checkpoint {path}: {err}; a part registered by a plugin needs that plugin here too ({PLUGINS_ENV}=module)"
        ) from None


def _field(data: Mapping[str, Any], key: str, kind: type, expected: str, path: Path) -> Any:
    """``data[key]``, a field of the checkpoint ``path``, when it is absent (None) or a ``kind`` (a bool is not an
    int here).

    Raises:
        CheckpointError: a value of another type, named with ``expected`` (``"a whole number"``).
    """
    value = data.get(key)
    if value is None or (isinstance(value, kind) and (kind is bool or not isinstance(value, bool))):
        return value
    raise CheckpointError(f"checkpoint {path}: its {key!r} is {kind_of(value)}, not {expected}")


def _scalar(data: Mapping[str, Any], key: str, path: Path) -> float | None:
    """``data[key]``, a number or a one-element tensor (a module's buffer) of the checkpoint ``path``, as a number
    (None when absent).

    Raises:
        CheckpointError: anything else.
    """
    value = data.get(key)
    if isinstance(value, torch.Tensor) and value.numel() == 1 and not value.is_complex():
        value = value.item()
    if value is None or (isinstance(value, int | float) and not isinstance(value, bool)):
        return value
    raise CheckpointError(f"checkpoint {path}: its {key!r} is {kind_of(value)}, not a number")


def _load_weights(model: Unicorn, state: Any, path: Path, field: str) -> None:
    """Load ``state`` (the checkpoint's ``field``) strictly, except for the perceptual loss's weights (not rebuilt).

    Raises:
        CheckpointError: ``state`` is not a dict, or its weights do not fit the model (:func:`weights_misfit`).
    """
    if not isinstance(state, Mapping):
        raise CheckpointError(f"checkpoint {path}: its {field} is {kind_of(state)}, not a dict of weights")
    state = {k: v for k, v in state.items() if not (isinstance(k, str) and k.startswith("perceptual."))}
    misfit = weights_misfit(state, model.state_dict())
    if misfit:
        raise CheckpointError(f"checkpoint {path} does not fit the model built from its own config: {misfit}")
    model.load_state_dict(state)


def load_model(
    path: str | os.PathLike,
    map_location: str | torch.device = "cpu",
    overrides: Mapping[str, Any] | None = None,
    trust: bool = False,
) -> tuple[Unicorn, CheckpointInfo]:
    """Build the model stored in a checkpoint of any supported format and load its weights.

    Args:
        path: a released ``.pkl``, a Lightning ``.ckpt`` or a :func:`save_model` file.
        map_location: where the weights are loaded, and the model returned (a device); ``torch.load``'s remappings
            (a dict, a function) leave the model on the CPU.
        overrides: model config groups to change, e.g. ``{"template": {"level": 4}}`` for the finer mesh of
            UNICORN's keypoint evaluation (the template and the renderer are not part of the weights).
        trust: allow full unpickling, for files from a source you trust (it can run arbitrary code).

    Returns:
        ``(model, info)``: the model in eval mode on ``map_location``, and a :class:`CheckpointInfo`.

    Raises:
        FileNotFoundError: no such file.
        UnsafeCheckpointError: the file needs full unpickling and ``trust`` is False.
        CheckpointError: unreadable or corrupted file, unknown layout, a field of the wrong type, model settings
            of another version, weights that do not fit, or NaN, infinite or negative-variance weights
            (:func:`check_weight_values`; each named in one line).
        ModelTooLargeError: a stored image, texture or model size above the limits, refused before building it.
        MapLocationError: ``map_location`` is not a device of this machine (``"cuda:7"`` without that GPU), checked
            before the file is read.
        ValueError: ``map_location`` is the meta device.
    """
    path = Path(path).expanduser()
    device = model_device(map_location)
    data = read_checkpoint(path, map_location, trust=trust)
    loader = _LOADERS.get(checkpoint_format(data))
    if loader is None:
        keys = sorted(map(str, data))[:10]
        raise CheckpointError(
            f"{path} is not a UNICORN checkpoint (keys {keys}): expected a released .pkl (model_state), a "
            "unicorn-train .ckpt (state_dict + hyper_parameters) or a unicorn.io.save_model file"
        )
    model, info = loader(data, path, overrides)
    check_weight_values(model, path)
    info.run_dir = run_of_checkpoint(path)
    if info.dataset is None:
        info.dataset = run_dataset(info.run_dir)
    return (model if device is None else model.to(device)).eval(), info


def _load_reference(
    data: Mapping[str, Any], path: Path, overrides: Mapping[str, Any] | None
) -> tuple[Unicorn, CheckpointInfo]:
    """A released ``.pkl``, converted (:func:`~unicorn.io.reference_checkpoints.load_reference_checkpoint`)."""
    try:
        model = reference_model(data, f"released checkpoint {path}", **copy.deepcopy(dict(overrides or {})))
    except ModelTooLargeError:
        raise  # names the file already
    except (KeyError, ValueError) as err:
        raise CheckpointError(f"released checkpoint {path} could not be converted: {err}") from err
    return model, CheckpointInfo(path, "reference", epoch=data.get("epoch"))  # its type checked by the conversion


def _load_lightning(
    data: Mapping[str, Any], path: Path, overrides: Mapping[str, Any] | None
) -> tuple[Unicorn, CheckpointInfo]:
    """A ``unicorn-train`` ``.ckpt``: the model from its ``model`` hyper-parameter, the ``model.`` weights."""
    hparams = _to_plain(data["hyper_parameters"])
    if not isinstance(hparams, Mapping) or "model" not in hparams:
        raise CheckpointError(
            f"Lightning checkpoint {path} has no 'model' hyper-parameter: it was not written by unicorn-train"
        )
    state = data["state_dict"]
    if not isinstance(state, Mapping):
        raise CheckpointError(f"checkpoint {path}: its 'state_dict' is {kind_of(state)}, not a dict of weights")
    weights = {k[len("model.") :]: v for k, v in state.items() if isinstance(k, str) and k.startswith("model.")}
    if not weights:
        raise CheckpointError(f"Lightning checkpoint {path} holds no 'model.' weights")
    epoch = _field(data, "epoch", int, "a whole number", path)
    step = _field(data, "global_step", int, "a whole number", path)
    p, stage = _scalar(state, "texture_average_p", path), _scalar(state, "stage", path)
    model = _stored_model(hparams["model"], path, "hyper-parameter 'model'", overrides)
    _load_weights(model, weights, path, "'state_dict'")
    info = CheckpointInfo(
        path,
        "lightning",
        epoch=epoch,
        step=step,
        average_texture=p is not None and p >= 1.0,
        extra={"stage": None if stage is None else int(stage)},
    )
    return model, info


def _load_plain(
    data: Mapping[str, Any], path: Path, overrides: Mapping[str, Any] | None
) -> tuple[Unicorn, CheckpointInfo]:
    """A :func:`save_model` file: its config, weights and ``info``."""
    for key in ("config", "state_dict"):
        if key not in data:
            raise CheckpointError(
                f"checkpoint {path} has no {key!r}: a damaged or hand-made unicorn.io.save_model file"
            )
    meta = dict(_field(data, "info", Mapping, "a dict", path) or {})
    info = CheckpointInfo(
        path,
        "plain",
        epoch=_field(meta, "epoch", int, "a whole number", path),
        step=_field(meta, "step", int, "a whole number", path),
        average_texture=bool(_field(meta, "average_texture", bool, "true or false", path)),
        dataset=_field(meta, "dataset", dict, "a dict (name, root...)", path),
        extra={k: v for k, v in meta.items() if k not in ("epoch", "step", "average_texture", "dataset")},
    )
    model = _stored_model(data["config"], path, "'config'", overrides)
    _load_weights(model, data["state_dict"], path, "'state_dict'")
    return model, info


#: how each checkpoint format (:func:`checkpoint_format`) is loaded
_LOADERS = {"reference": _load_reference, "lightning": _load_lightning, "plain": _load_plain}


def check_weight_values(model: torch.nn.Module, path: str | os.PathLike) -> None:
    """Refuse weights no prediction can come from: a NaN or infinite value in any floating-point weight or buffer, or
    a negative running variance of a batch normalisation (whose square root the layer takes).

    Raises:
        CheckpointError: names the first such tensor.
    """
    for name, value in model.state_dict().items():
        if not value.is_floating_point():
            continue
        if not bool(torch.isfinite(value).all()):
            raise CheckpointError(f"checkpoint {path}: its weight {name} holds NaN or infinite values")
        if name.endswith("running_var") and bool((value < 0).any()):
            raise CheckpointError(f"checkpoint {path}: its batch-norm running variance {name} holds negative values")


#: the state of a model that ``init_from`` does not take from its file: the perceptual loss's fixed VGG16 and the
#: renderer's settings (the run's configured ``renderer.background_color``)
_NOT_LEARNED = ("perceptual.", "renderer.")


def init_weights(model: Unicorn, path: str | os.PathLike, trust: bool = False) -> CheckpointInfo:
    """Load the weights of any checkpoint (:func:`load_model`'s formats) into ``model``, in place: training started
    from a released model or a :func:`save_model` file (``unicorn-train init_from=...``).

    Every learned weight must fit: the same networks, the same sizes. The perceptual loss and the renderer (its
    ``background_color``, a setting of the run) are not part of it: ``model`` keeps its own.

    Raises:
        CheckpointError: the file cannot be loaded, or its weights do not fit ``model``'s configuration.
    """
    source, info = load_model(path, trust=trust)
    state = {k: v for k, v in source.state_dict().items() if not k.startswith(_NOT_LEARNED)}
    own = {k: v for k, v in model.state_dict().items() if not k.startswith(_NOT_LEARNED)}
    check_weights_fit(state, own, "init_from", path)
    model.load_state_dict(state, strict=False)  # every key checked above; the rest keeps the model's own
    return info


def check_weights_fit(
    saved: Mapping[str, Any], own: Mapping[str, torch.Tensor], option: str, path: str | os.PathLike
) -> None:
    """Refuse saved weights that do not fit a model's (:func:`weights_misfit`), in one line.

    Args:
        saved: the checkpoint's weights by name.
        own: the configured model's (``state_dict()``).
        option: the setting that named the file (``"init_from"``, ``"ckpt_path"``).
        path: the file.

    Raises:
        CheckpointError: names that are missing or unexpected, values that are not tensors or of other shapes.
    """
    misfit = weights_misfit(saved, own)
    if misfit:
        raise CheckpointError(
            f"{option}: the weights of {path} do not fit the configured model (choose the model and dataset "
            f"settings it was trained with, e.g. model=big): {misfit}"
        )


def weights_misfit(saved: Mapping[str, Any], own: Mapping[str, torch.Tensor], strict: bool = True) -> str | None:
    """What keeps ``load_state_dict(saved)`` from loading into a model whose ``state_dict()`` is ``own`` (which
    would raise a RuntimeError of many lines), checked first: the first few names missing or unexpected (only when
    ``strict``), then of the names in both, values that are not tensors or tensors of other shapes, each with its
    shape in the file and in the model; None when every weight fits.
    """
    missing, unexpected = (sorted(set(own) - set(saved)), sorted(set(saved) - set(own))) if strict else ([], [])
    misfit = [
        f"{k} {kind_of(saved[k])} in the file, not a tensor"
        if not isinstance(saved[k], torch.Tensor)
        else f"{k} {list(saved[k].shape)} in the file, {list(v.shape)} in the model"
        for k, v in own.items()
        if k in saved and not (isinstance(saved[k], torch.Tensor) and saved[k].shape == v.shape)
    ]
    if not (missing or unexpected or misfit):
        return None
    more = f" and {len(misfit) - 4} more" if len(misfit) > 4 else ""
    return f"missing {missing[:4]}, unexpected {unexpected[:4]}, other sizes or types [{'; '.join(misfit[:4])}{more}]"


def save_model(model: Unicorn, path: str | os.PathLike, *, overwrite: bool = False, **info: Any) -> Path:
    """Write a plain checkpoint (config, weights and ``info``) that :func:`load_model` reads.

    The file is written atomically and carries a hash of its content (see :mod:`unicorn.io.serialization`); the
    temporary file a killed save to ``path`` left beside it is deleted.

    Args:
        model: the model.
        path: the file to write (folders are created).
        overwrite: replace a file at ``path``; otherwise one there is an error and nothing is written.
        **info: metadata kept with it: ``epoch``, ``step``, ``average_texture``, ``dataset`` (a dict with ``name``
            and ``root``) or anything else: numbers, strings, None, lists and dicts of them, tensors; paths are
            kept as strings and dataclasses (a :class:`CheckpointInfo`) as dicts.

    Returns:
        ``path`` as a Path.

    Raises:
        TypeError: a value of ``info`` that :func:`load_model` could not read back (it loads plain values only),
            named before anything is written.
        FileExistsError: a file is at ``path`` and ``overwrite`` is False.
        IsADirectoryError: ``path`` is a folder, whatever ``overwrite``.
        NotADirectoryError: a file stands where a folder above ``path`` goes (the message names it).
    """
    path = Path(path).expanduser()
    if path.is_dir() and not path.is_symlink():  # a link is replaced, not followed
        raise IsADirectoryError(f"{path} is a folder: save_model writes a file; choose a file name (model.pt)")
    if not overwrite and (path.exists() or path.is_symlink()):
        raise FileExistsError(f"{path} exists: pass overwrite=True to replace it with the model")
    plain = {key: _plain_value(value, key) for key, value in info.items()}
    state = {k: v.detach().cpu() for k, v in model.state_dict().items() if not k.startswith("perceptual.")}
    return atomic_save(
        {"format": PLAIN_FORMAT, "config": copy.deepcopy(model.config), "state_dict": state, "info": plain}, path
    )


def _plain_value(value: Any, name: str) -> Any:
    """``value`` as the plain types a checkpoint loaded without trust holds (see :func:`save_model`)."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, numbers.Integral | numbers.Real):  # numpy's scalars
        return int(value) if isinstance(value, numbers.Integral) else float(value)
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping) and all(isinstance(k, str) for k in value):
        return {k: _plain_value(v, f"{name}.{k}") for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain_value(v, f"{name}[{i}]") for i, v in enumerate(value)]
    raise TypeError(
        f"save_model: {name} is a {type(value).__name__}, which load_model would refuse to read back (it loads plain "
        "values only): pass numbers, strings, lists and dicts"
    )
