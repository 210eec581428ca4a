"""Validation of a composed training config and its translation into the model's configuration.

:func:`validate` is what ``unicorn-train`` runs right after Hydra composed the config: it merges the config
onto the structured schema (:class:`~unicorn.config.schema.TrainConfig`: unknown keys and wrong types fail
there, naming the key) and checks the relations between values. :func:`model_config` turns the validated
``model`` and ``renderer`` groups into the mapping :class:`unicorn.model.Unicorn` takes.
"""

from __future__ import annotations

import typing
from collections.abc import Mapping, Sequence
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from unicorn.checks import MAX_SEED, is_number, is_seed
from unicorn.config.schema import HELDOUT_SPLITS, N_STAGES, OPTIM_CHOICES, SCHEDULE_MODES, SPLITS, TrainConfig
from unicorn.data.common import OnError
from unicorn.data.registry import DATASETS, stored_image_size
from unicorn.errors import UserError
from unicorn.model import check_model_size
from unicorn.model.compile import COMPILE_MODES, COMPILE_SCOPES
from unicorn.model.config import CODE_BRANCHES, allowed_values, check_model_config
from unicorn.model.ranges import check_ranges
from unicorn.objectives.loss_factory import check_loss_choices
from unicorn.registry import keyword_options
from unicorn.render import BACKGROUND_COLOR, RenderError, check_render_option, get_renderer_class, list_renderers

__all__ = ["ConfigError", "check_optim", "model_config", "renderer_settings", "validate"]

_CAMERA_DEFAULTS = {"znear": 1.0, "zfar": 100.0}
#: the one camera the model builds (``renderer.camera._target_`` in ``conf/renderer/*.yaml`` names it)
_CAMERA_TARGET = "unicorn.geometry.cameras.PerspectiveCamera"


class ConfigError(UserError, ValueError):
    """A training configuration that cannot be used (the message names the key)."""


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


def validate(cfg: DictConfig | Mapping[str, Any]) -> DictConfig:
    """Merge ``cfg`` onto the schema and check it; returns the typed config (a new object).

    Interpolations stay unresolved in the result (``${hydra:...}`` only resolves inside a Hydra run), but
    every value checked here is resolved once.

    Raises:
        ConfigError: an unknown key, a wrong type or inconsistent values, with the offending key's name.
    """
    try:
        typed = OmegaConf.merge(OmegaConf.structured(TrainConfig), cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(f"invalid training config: {_omegaconf_message(err)}") from None
    # the schema has no default root: every dataset preset names one (`???`: to be given on the command line)
    _check(
        not OmegaConf.is_missing(typed.dataset, "root"),
        f"dataset.root is required by dataset {typed.dataset.name!r}: give the folder of its data "
        "(dataset.root=/path/to/data)",
    )
    try:
        _check_paths(typed)
        _check_values(typed)
    except OmegaConfBaseException as err:
        raise ConfigError(f"invalid training config: {_omegaconf_message(err)}") from None
    except (ValueError, TypeError) as err:
        if isinstance(err, UserError):  # already one line naming the key
            raise
        # a check inside a part the config builds (a camera, a pose range): its message names the setting
        raise ConfigError(f"invalid training config: {err}") from None
    return typed


def _omegaconf_message(err: OmegaConfBaseException) -> str:
    """OmegaConf's error in one line, ``<key>: <what>``: its message's first line, without the lines it adds (the
    key, the config's classes)."""
    lines = str(err).strip().splitlines() or [type(err).__name__]
    key = getattr(err, "full_key", None)
    return f"{key}: {lines[0]}" if key else lines[0]


#: the settings that name a file or folder, and what to give instead of an empty value
_PATH_SETTINGS = {
    "dataset.root": "give the folder of its data (dataset.root=/path/to/data)",
    "init_from": "name a weights file (a released .pkl, a .ckpt), or leave it out",
    "paths.log_dir": "give the folder the runs go under (default: outputs)",
    # from the environment: an exported but empty variable (UNICORN_CACHE=) is read as the empty string
    "paths.cache_dir": "set UNICORN_CACHE to a folder, or unset it for ~/.cache/unicorn",
    "paths.vgg16": "set UNICORN_VGG16 to the VGG16 weights file, or unset it for torch's hub cache",
}


def _check_paths(cfg: DictConfig) -> None:
    """Refuse an empty path setting (``dataset.root=$DATA`` with ``DATA`` unset): alone it names the current folder
    (where the synthetic dataset would be generated), and at the start of another path
    (``${paths.log_dir}/${task_name}``, the run's folder) the file system's root."""
    for key, instead in _PATH_SETTINGS.items():
        value = OmegaConf.select(cfg, key)
        _check(value is None or str(value).strip() != "", f"{key} is empty: {instead}")


def check_optim(optim: Mapping[str, Any], prefix: str = "optim.") -> None:
    """The value checks of the optimisation settings (:class:`~unicorn.config.schema.OptimConfig`'s keys).

    Raises:
        ValueError: the first bad value, named with its key.
    """
    lr, betas = optim["lr"], list(optim["betas"])
    _check(is_number(lr) and lr > 0, f"{prefix}lr must be a finite number > 0, got {lr}")
    _check(len(betas) == 2, f"{prefix}betas needs two values, got {betas}")
    _check(all(is_number(b) and 0 <= b < 1 for b in betas), f"{prefix}betas must lie in [0, 1), got {betas}")
    for key, allowed in OPTIM_CHOICES.items():
        _check(optim[key] in allowed, f"{prefix}{key} must be one of {allowed}, got {optim[key]!r}")
    _check(optim["lr_drop_step"] is None or optim["lr_drop_step"] >= 0, f"{prefix}lr_drop_step must be null or >= 0")


def _check_values(cfg: DictConfig) -> None:
    """The checks types cannot express: the ranges declared in the schema, then the relations between values."""
    try:
        check_ranges(cfg, TrainConfig)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    _check_seed("seed", cfg.seed)
    _check(
        _is_folder_name(cfg.task_name),
        f"task_name must be a folder name, not a path (no / or \\, not . or ..), got {cfg.task_name!r}",
    )
    _check(cfg.dataset.name in DATASETS, f"dataset.name {cfg.dataset.name!r} is not one of {DATASETS.names()}")
    _check_model(cfg)
    _check_sizes(cfg)
    _check_dataset(cfg.dataset)
    stored = stored_image_size(cfg.dataset.name, cfg.dataset.synthetic)
    _check(
        stored is None or stored == cfg.dataset.img_size,
        f"dataset.img_size={cfg.dataset.img_size}, but the {cfg.dataset.name} images are {stored} px "
        f"(dataset.synthetic.image_size); set both to the same size",
    )
    _check_schedule(cfg.schedule)
    check_optim(cfg.optim)  # raises ConfigError itself
    _check_trainer(cfg.trainer)
    _check_callbacks_and_loggers(cfg)
    _check(
        cfg.init_from is None or cfg.ckpt_path in (None, "last"),
        "init_from and ckpt_path exclude each other: ckpt_path resumes a run, init_from starts a new one from weights "
        "(with ckpt_path=last, init_from starts the run when its folder holds no checkpoint yet)",
    )
    on_error, d = typing.get_args(OnError), cfg.dataset
    _check(d.on_error in on_error, f"dataset.on_error must be one of {on_error}, got {d.on_error!r}")
    workers, pin = d.num_workers, d.pin_memory
    _check(
        workers is None or workers == "auto" or (type(workers) is int and workers >= 0),
        f"dataset.num_workers must be >= 0, or auto (chosen from the machine), got {workers!r}",
    )
    _check(
        pin is None or pin == "auto" or isinstance(pin, bool),
        f"dataset.pin_memory must be true, false or auto (when training on CUDA), got {pin!r}",
    )


def _is_folder_name(name: str) -> bool:
    """A name a folder can take on every system, not a path: no separator, not ``.`` or ``..``, not empty."""
    return bool(name.strip()) and name not in (".", "..") and not any(c in name for c in "/\\\0")


def _plain(value: Any) -> Any:
    """A config list as a plain list (for messages and checks); other values as they are."""
    return OmegaConf.to_container(value) if isinstance(value, ListConfig) else value


def _check_seed(key: str, value: Any) -> None:
    _check(is_seed(value), f"{key} must be a whole number in [0, {MAX_SEED}] (numpy's seeds), got {value}")


def _check_dataset(d: DictConfig) -> None:
    """The dataset's seed, and for the generated dataset its categories and generation settings."""
    from unicorn.checks import SizeLimitError
    from unicorn.data.images import DatasetError
    from unicorn.data.synthetic.writer import check_synthetic_settings

    _check_seed("dataset.seed", d.seed)
    _check(
        d.categories is None or DATASETS.get(d.name).by_category,
        f"dataset.categories={_plain(d.categories)!r}, but dataset {d.name} holds one category and would ignore it: "
        "drop it (dataset.categories=null)",
    )
    # an experiment's options for its own dataset (cub's jitter) stay when the dataset group is switched after it
    accepted = sorted(DATASETS.get(d.name).options)
    unknown = sorted(set(d.options or {}) - set(accepted))
    drop = " ".join(f"~dataset.options.{key}" for key in unknown)
    _check(
        not unknown,
        f"dataset.options {unknown} are not taken by dataset {d.name} (its options: {accepted}); an experiment may "
        f"set them for another dataset: drop them with {drop}",
    )
    if d.name != "synthetic":
        return
    categories = _plain(d.categories)
    synthetic = OmegaConf.to_container(d.synthetic, resolve=True) if d.synthetic is not None else {}
    try:
        check_synthetic_settings(categories, synthetic)
    except (DatasetError, SizeLimitError) as err:
        raise ConfigError(f"dataset.synthetic: {err}") from None


def _check_model(cfg: DictConfig) -> None:
    """The model's own checks on the configuration it will get, then its relations to the data and the stages."""
    m = cfg.model
    composites = allowed_values("renderer.composite")
    _check(m.composite in composites, f"model.composite must be one of {composites}, got {m.composite!r}")
    _check(
        m.compile is None or m.compile in COMPILE_MODES,
        f"model.compile must be null or one of {COMPILE_MODES}, got {m.compile!r}",
    )
    _check(
        m.compile_scope in COMPILE_SCOPES,
        f"model.compile_scope must be one of {COMPILE_SCOPES}, got {m.compile_scope!r}",
    )
    _check(
        m.compile_scope != "step" or cfg.optim.sync_free is not False,
        "model.compile_scope=step compiles the steps without host reads, but optim.sync_free is false",
    )
    # before the model config, which reads each first stage's size
    codes = {name: m[name].code_dim for name in CODE_BRANCHES if m[name] is not None}  # no background model: None
    for name, code_dim in codes.items():
        dims = list(m.stages[name])
        key = f"model.stages.{name}"
        _check(len(dims) == N_STAGES, f"{key} needs {N_STAGES} sizes (one per stage), got {dims}")
        _check(all(0 <= d <= code_dim for d in dims), f"{key} = {dims} must lie in [0, {name} code_dim={code_dim}]")
        _check(all(a <= b for a, b in zip(dims, dims[1:])), f"{key} = {dims} must not decrease")
    try:
        config = model_config(cfg)
        check_model_config(config, prefix="model.")
        check_loss_choices(config["loss"], prefix="model.")
    except ValueError as err:
        raise ConfigError(str(err)) from None
    _check(
        m.image_size == cfg.dataset.img_size,
        f"model.image_size ({m.image_size}) differs from dataset.img_size ({cfg.dataset.img_size})",
    )
    size = cfg.renderer.get("image_size", cfg.dataset.img_size)  # the renderer renders at the model's size
    _check(
        size == cfg.dataset.img_size,
        f"renderer.image_size ({size}) differs from dataset.img_size ({cfg.dataset.img_size}): the renderer "
        "renders at the model's image size; leave renderer.image_size out",
    )
    _check(
        cfg.dataset.batch_size <= m.loss.memory_size,
        f"dataset.batch_size ({cfg.dataset.batch_size}) exceeds model.loss.memory_size ({m.loss.memory_size})",
    )


def _check_sizes(cfg: DictConfig) -> None:
    """Bound what the settings make the run allocate, before anything is built (the limits the commands share:
    :func:`unicorn.checks.check_limit`): a training image and a texture map against the image limits, the model
    against ``UNICORN_MAX_MODEL_PARAMS``, the pose step's render (a batch times the pose candidates) against the
    renderer's fragment limit, and the point counts of the evaluation after training.

    Raises:
        unicorn.checks.SizeLimitError: the message names the setting and the limit.
    """
    from unicorn.checks import SizeLimitError
    from unicorn.data.images import check_image_size
    from unicorn.geometry.cameras import PerspectiveCamera
    from unicorn.metrics.sampling import check_point_count
    from unicorn.render import RenderSizeError, build_renderer, check_render_size

    d, m = cfg.dataset, cfg.model
    if cfg.get("evaluate") is not None and cfg.evaluate.get("enabled", False):  # scored after training: checked now
        for key in ("num_points", "shape_points"):
            check_point_count(f"evaluate.{key}={cfg.evaluate[key]}", cfg.evaluate[key])
    check_image_size(f"dataset.img_size={d.img_size}", "a training image", d.img_size)
    check_image_size(f"model.texture.size={m.texture.size}", "a texture map", m.texture.size)
    config = model_config(cfg)
    check_model_size(config, "model", error=SizeLimitError)
    settings = config["renderer"]
    try:
        camera = PerspectiveCamera(fov=settings["fov"], focal_length=settings["focal_length"])
    except ValueError as err:  # "fov must be ...", "focal_length must be ..."
        raise ConfigError(f"renderer.camera.{err}") from None
    renderer = build_renderer(settings["name"], image_size=d.img_size, camera=camera, **settings["options"])
    rasterizer = renderer.rasterizer
    candidates = m.pose.n_elev * m.pose.n_azim
    try:
        check_render_size(
            d.batch_size * candidates, rasterizer.raster_size, rasterizer.faces_per_pixel, rasterizer.max_bytes
        )
    except RenderSizeError as err:
        raise ConfigError(
            f"dataset.img_size={d.img_size}: the pose step renders dataset.batch_size={d.batch_size} images x "
            f"{candidates} pose candidates at once: {err}"
        ) from None


def _check_schedule(s: DictConfig) -> None:
    _check(s.mode in SCHEDULE_MODES, f"schedule.mode must be fixed or plateau, got {s.mode!r}")
    ms = list(s.milestones)
    _check(len(ms) == N_STAGES - 1, f"schedule.milestones needs {N_STAGES - 1} iterations (stages 2-4), got {ms}")
    _check(all(a < b for a, b in zip([0, *ms], ms)), f"schedule.milestones must increase from > 0, got {ms}")


def _check_trainer(t: DictConfig) -> None:
    _check(
        t.deterministic is None or isinstance(t.deterministic, bool) or t.deterministic == "warn",
        f"trainer.deterministic must be true, false, warn or null, got {t.deterministic!r}",
    )
    _check(
        _devices_ok(t.devices),
        f"trainer.devices must be 'auto', a number of devices (-1: all) or a list of device indices such as [0, 1], "
        f"got {t.devices!r}",
    )
    precisions = _lightning_precisions()
    _check(t.precision in precisions, f"trainer.precision must be one of {precisions}, got {t.precision!r}")
    _check(
        str(t.precision) not in _CAST_PRECISIONS,
        f"trainer.precision={t.precision} casts the whole model, whose renderer, pose candidates and scale stay in "
        "float32: use bf16-mixed (or 16-mixed on CUDA), which runs the networks in the lower precision",
    )
    if isinstance(t.strategy, str):
        from lightning.pytorch.strategies import StrategyRegistry

        strategies = ["auto", *StrategyRegistry.available_strategies()]
        _check(t.strategy in strategies, f"trainer.strategy must be one of {strategies}, got {t.strategy!r}")
    limit = t.limit_val_batches  # Lightning's: a number of batches, or a fraction of them (null: all)
    _check(
        limit is None or (is_number(limit) and limit >= 0 and (limit <= 1 or float(limit).is_integer())),
        f"trainer.limit_val_batches must be a number of batches >= 0 or a fraction in [0, 1], got {limit!r}",
    )
    _check(
        t.val_check_interval is None or t.val_check_interval >= 1,
        "trainer.val_check_interval must be null (no validation) or a number of iterations >= 1",
    )
    strategy = t.strategy if isinstance(t.strategy, str) else None
    _check(
        strategy not in ("ddp", "ddp_spawn", "ddp_fork", "ddp_notebook"),
        f"trainer.strategy={strategy}: the pose / 3D alternation leaves half of the parameters without gradient "
        "at every step; use ddp_find_unused_parameters_true (or ddp_spawn_find_unused_parameters_true)",
    )
    _check_accelerator(t.accelerator)
    if strategy == "auto":
        per_node = _device_count(t.accelerator, t.devices)
        if per_node is not None and per_node * t.num_nodes > 1:
            if t.num_nodes > 1:
                what = f"trainer.num_nodes={t.num_nodes}"
            elif _devices_text(t.devices) in ("auto", "-1"):
                what = f"trainer.devices={_devices_text(t.devices)} ({per_node} devices on this machine)"
            else:
                what = f"trainer.devices={_devices_text(t.devices)}"
            one = "trainer.devices=1" + (" trainer.num_nodes=1" if t.num_nodes > 1 else "")
            raise ConfigError(
                f"trainer.strategy=auto with {what} runs Lightning's plain DDP, which stops at the first step: the "
                "pose / 3D alternation leaves part of the parameters without gradient at every step; use "
                "trainer.strategy=ddp_find_unused_parameters_true (as trainer=ddp and trainer=ddp_cpu do), or one "
                f"device ({one})"
            )


def _check_accelerator(accelerator: Any) -> None:
    """An accelerator Lightning has registered (``tpu``...) whose package is not installed, named before the run
    is built (Lightning raises a ``ModuleNotFoundError`` when it builds the trainer). Names Lightning does not know
    and accelerators this machine lacks are the trainer's to report."""
    from lightning.pytorch.accelerators import AcceleratorRegistry

    if not isinstance(accelerator, str) or accelerator not in AcceleratorRegistry:
        return
    try:
        AcceleratorRegistry.get(accelerator)
    except ImportError as err:  # e.g. tpu: "Requirement 'torch_xla>=1.13' not met. HINT: ..."
        raise ConfigError(f"trainer.accelerator={accelerator} needs a package that is not installed: {err}") from None


def _devices_text(devices: Any) -> str:
    """``trainer.devices`` as written on the command line (``auto``, ``2``, ``[0, 1]``)."""
    if isinstance(devices, ListConfig):
        devices = OmegaConf.to_container(devices)
    return str(devices).strip() if isinstance(devices, str) else str(devices)


def _device_count(accelerator: Any, devices: Any) -> int | None:
    """How many devices (one process each on every node) Lightning's trainer runs on with these flags, as it counts
    them (``auto`` and ``-1``: every device of this machine); None where Lightning itself refuses them (a device this
    machine lacks, a list of CPUs) or runs no DDP (TPUs), for the trainer to report."""
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from lightning.pytorch.accelerators import AcceleratorRegistry, CUDAAccelerator, MPSAccelerator

    if not isinstance(accelerator, str):
        return None
    if accelerator in ("auto", "gpu"):  # as Lightning picks them (a TPU aside)
        if MPSAccelerator.is_available():
            accelerator = "mps"
        elif CUDAAccelerator.is_available():
            accelerator = "cuda"
        elif accelerator == "auto":
            accelerator = "cpu"
    if accelerator not in ("cpu", "cuda", "mps"):
        return None
    if isinstance(devices, ListConfig):
        devices = OmegaConf.to_container(devices)
    try:
        cls = type(AcceleratorRegistry.get(accelerator))
        if isinstance(devices, str) and devices.strip() == "auto":
            devices = cls.auto_device_count()
        return len(cls.get_parallel_devices(cls.parse_devices(devices)))
    except (MisconfigurationException, ValueError, TypeError):
        return None


def _devices_ok(devices: Any) -> bool:
    """Lightning's forms of ``devices``: ``"auto"``, a count (-1: all; 0 is refused when the trainer is built), a
    list of indices, or these as a string (``"2"``, ``"0,1"``)."""
    if isinstance(devices, str):
        text = devices.strip()
        if text == "auto":
            return True
        if "," in text:
            return all(part.strip().isdigit() for part in text.split(",") if part.strip())
        return text.lstrip("-").isdigit() and int(text) >= -1
    if isinstance(devices, bool):
        return False
    if isinstance(devices, int):
        return devices >= -1
    if isinstance(devices, Sequence):
        return len(devices) > 0 and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in devices)
    return False


#: Lightning's precisions that cast the model's weights (the networks, and the float32 renderer's inputs with them)
_CAST_PRECISIONS = ("16-true", "bf16-true", "transformer-engine", "transformer-engine-float16")


def _lightning_precisions() -> tuple[Any, ...]:
    """Every ``precision`` Lightning's trainer takes (``"32-true"``, ``"bf16-mixed"``, ``16``...)."""
    from lightning.fabric.connector import _PRECISION_INPUT

    return tuple(value for literal in typing.get_args(_PRECISION_INPUT) for value in typing.get_args(literal))


def _check_callbacks_and_loggers(cfg: DictConfig) -> None:
    h, e, c = cfg.callbacks.heldout, cfg.evaluate, cfg.callbacks.checkpoint
    _check(
        c is None or c.keep != 0 or c.save_last,
        "callbacks.checkpoint.keep=0 with save_last=false keeps no checkpoint: the trained weights would be lost "
        "when the run ends; keep one (keep=1) or save last.ckpt (save_last=true)",
    )
    if h is not None:
        _check(h.split in HELDOUT_SPLITS, f"callbacks.heldout.split must be val or test, got {h.split!r}")
    _check(e.split in SPLITS, f"evaluate.split must be train, val or test, got {e.split!r}")
    for name, node in cfg.logger.items():
        _check(
            node is None or (isinstance(node, Mapping) and "_target_" in node),
            f"logger.{name} must be null or have a _target_",
        )
    for name, node in cfg.callbacks.extra.items():
        _check(isinstance(node, Mapping) and "_target_" in node, f"callbacks.extra.{name} needs a _target_")


def renderer_settings(renderer: Mapping[str, Any]) -> dict[str, Any]:
    """The model's ``renderer`` group from a ``conf/renderer/*.yaml`` node.

    ``name`` is the registered backend (:func:`unicorn.render.list_renderers`); ``camera.fov`` /
    ``camera.focal_length`` and ``background_color`` become the model's camera and colour, the remaining
    keys the backend's options. ``image_size`` is ignored (the model's image size wins).

    Raises:
        ConfigError: no or an unregistered ``name``, an option the backend does not take, or a ``camera._target_``
            other than the model's perspective camera.
    """
    cfg = OmegaConf.to_container(renderer, resolve=True) if isinstance(renderer, DictConfig) else dict(renderer)
    name = cfg.pop("name", None)
    _check(name in list_renderers(), f"renderer.name must be one of {list_renderers()}, got {name!r}")
    cls = get_renderer_class(name)
    cfg.pop("image_size", None)
    camera = dict(cfg.pop("camera", None) or {})
    target = camera.pop("_target_", _CAMERA_TARGET)
    _check(
        target == _CAMERA_TARGET,
        f"renderer.camera._target_={target} is not supported: the model's camera is {_CAMERA_TARGET} "
        "(renderer.camera.fov or focal_length set it)",
    )
    fov, focal = camera.pop("fov", None), camera.pop("focal_length", None)
    _check((fov is None) != (focal is None), "renderer.camera needs exactly one of fov and focal_length")
    taken = keyword_options(cls)  # None: it takes any keyword (**kwargs) and checks its own options
    accepted = None if taken is None else set(taken) - {"camera", "image_size"}
    for key, value in camera.items():
        if accepted is not None and key in accepted and key not in cfg:
            cfg[key] = value  # e.g. SoftRas depth normalisation
        else:
            _check(
                key in _CAMERA_DEFAULTS and value == _CAMERA_DEFAULTS[key],
                f"renderer.camera.{key}={value} is not supported by the model's camera",
            )
    background_color = cfg.pop("background_color", BACKGROUND_COLOR)
    if isinstance(background_color, Sequence) and not isinstance(background_color, str):
        background_color = tuple(background_color)  # else as given (0.5, "white"), for the model's check to name
    unknown = [] if accepted is None else sorted(set(cfg) - accepted)
    drop = " ".join(f"~renderer.{key}" for key in unknown)
    _check(
        not unknown,
        f"renderer options {unknown} are not accepted by {name!r} (its options besides camera and image_size: "
        f"{sorted(accepted or ())}); an experiment or family "
        f"may set them for another renderer: drop them with {drop}",
    )
    for key, value in cfg.items():
        try:
            check_render_option(key, value)
        except RenderError as err:
            raise ConfigError(f"renderer.{err}") from None
    return {
        "name": name,
        "fov": fov,
        "focal_length": focal,
        "background_color": background_color,
        "options": cfg,
    }


def model_config(cfg: DictConfig) -> dict[str, Any]:
    """Configuration of :class:`unicorn.model.Unicorn` from a validated training config.

    Initial active code sizes are those of stage 1 (the stage callback sets them anyway).
    """
    model = OmegaConf.to_container(cfg.model, resolve=True)
    assert isinstance(model, dict)
    stages = model.pop("stages")
    model.pop("name")
    model.pop("compile")  # how the networks run, not what they are: unicorn.lit.run.fit applies it
    model.pop("compile_scope")
    renderer = renderer_settings(cfg.renderer)
    renderer["composite"] = model.pop("composite")
    model["renderer"] = renderer
    for name in CODE_BRANCHES:
        if model[name] is not None:  # no background model: None
            model[name]["active_dims"] = stages[name][0]
    for group in ("template", "pose"):
        for key, value in model[group].items():
            if isinstance(value, list):
                model[group][key] = tuple(value)
    return model
