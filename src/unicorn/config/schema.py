"""Structured schema of the training configuration (``conf/train.yaml`` and its groups).

:class:`TrainConfig` holds every key of a training run with its default. Importing this module registers its
defaults in Hydra's ConfigStore as :data:`SCHEMA_NAME`, the first entry of ``conf/train.yaml``'s defaults list:
a composed config starts from the schema's defaults, so every key exists (and can be overridden on the command
line, a misspelt one fails naming it) while the YAML files hold only what differs from these defaults.
:func:`unicorn.config.validate` merges the composed config onto the typed schema (a value of the wrong type or a
key added with ``+`` fails with the key's full name) and checks what types cannot express (milestones in order,
code sizes within the code, renderer options the backend accepts, ...).

The ``model`` group is the model's own configuration groups (:mod:`unicorn.model.config`, where every model key
and default is defined) plus ``name``, ``composite`` and ``stages``, the active code sizes of the four stages;
``renderer`` is one of ``conf/renderer/*.yaml`` (a registered backend's ``name`` plus its options) and is turned
into the model's renderer settings by :func:`unicorn.config.build.model_config`.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

from unicorn.model.config import ModelGroups, RendererConfig
from unicorn.model.ranges import ranged

__all__ = [
    "CallbacksConfig",
    "CheckpointConfig",
    "CurriculumConfig",
    "DatasetConfig",
    "DiagnosticsConfig",
    "EvalSettings",
    "EvaluateConfig",
    "EVAL_BATCH_SIZE",
    "FAST_EVAL",
    "FINAL_EVAL",
    "HELDOUT_SPLITS",
    "HeldOutConfig",
    "ImagesConfig",
    "ModelConfig",
    "N_STAGES",
    "OPTIM_CHOICES",
    "OptimConfig",
    "PathsConfig",
    "PlateauConfig",
    "REPORT_SAMPLES",
    "REPORT_TURNTABLE_FRAMES",
    "SCHEDULE_MODES",
    "SCHEMA_NAME",
    "SHAPE_POINTS",
    "SPLITS",
    "ScheduleConfig",
    "StageDimsConfig",
    "TextureAveragingConfig",
    "TrainConfig",
    "TrainerConfig",
    "store_schema",
]


#: UNICORN's stages of progressive conditioning (code sizes per stage, ``schedule.milestones`` between them)
N_STAGES = 4
#: dataset splits; the held-out evaluation during training scores one of the last two
SPLITS = ("train", "val", "test")
HELDOUT_SPLITS = SPLITS[1:]
#: ``schedule.mode``: fixed milestones, or a stage change when the 3D-step loss reaches a plateau
SCHEDULE_MODES = ("fixed", "plateau")
# The evaluation's defaults, here (the lowest floor the training config and unicorn.evaluation share) so that
# ``unicorn-eval`` (:class:`unicorn.evaluation.EvalOptions`) and the evaluations of a training run import them.
#: UNICORN's final protocol of the mesh metrics (``unicorn-eval``'s default)
FINAL_EVAL = {"num_points": 100_000, "icp_iterations": 100}
#: UNICORN's validation setting of the mesh metrics (``unicorn-eval --fast``, the evaluation after training)
FAST_EVAL = {"num_points": 50_000, "icp_iterations": 30}
#: images shown in an evaluation report (``report.png`` / ``report.html``): input, reconstruction, mask, views
REPORT_SAMPLES = 10
#: frames of each sample's turntable GIF in an evaluation report
REPORT_TURNTABLE_FRAMES = 16
#: images per forward pass of an evaluation
EVAL_BATCH_SIZE = 32
#: points per shape of the shape retrieval (``shape-top1`` ...; training's held-out scoring uses fewer)
SHAPE_POINTS = 2000


# ---------------------------------------------------------------------------------------------- model
@dataclass
class StageDimsConfig:
    """Active code sizes in stages 1 to 4 (the reference's small real-image model by default)."""

    shape: list[int] = field(default_factory=lambda: [0, 2, 8, 32])
    texture: list[int] = field(default_factory=lambda: [2, 8, 32, 128])
    background: list[int] = field(default_factory=lambda: [4, 8, 32, 128])


@dataclass
class ModelConfig(ModelGroups):
    """The model's groups (:class:`unicorn.model.config.ModelGroups`) plus the preset's name, the compositing
    rule (the model's ``renderer.composite``; the renderer itself is the ``renderer`` group) and the stages."""

    name: str = "small"
    composite: str = RendererConfig.composite  # direct | reference
    stages: StageDimsConfig = field(default_factory=StageDimsConfig)
    # torch.compile of the networks (unicorn.model.compile): null (eager), a mode, default | reduce-overhead |
    # max-autotune | max-autotune-no-cudagraphs, or cudagraphs (CUDA graphs of the eager kernels, no code
    # generation); where it cannot run, a warning says why and they run eagerly
    compile: str | None = None
    # what model.compile compiles: networks (each network and the reconstruction loss, in every step) | step (the
    # whole forward of the steps without host reads, networks, renderer and losses, as one graph per step kind:
    # with reduce-overhead or cudagraphs, CUDA graphs of whole steps; unicorn.lit.compiled)
    compile_scope: str = "networks"


# ---------------------------------------------------------------------------------------------- data
@dataclass
class DatasetConfig:
    """Arguments of :class:`unicorn.lit.UnicornDataModule` (``_target_`` may name a subclass). ``root`` has no
    default: every dataset preset says where its data is (``null``: the synthetic set in the cache)."""

    _target_: str = "unicorn.lit.UnicornDataModule"
    name: str = "synthetic"
    root: str | None = MISSING
    categories: Any = None  # one name or a list
    img_size: int = ranged(64, 8)
    batch_size: int = ranged(32, 1)
    # DataLoader workers: a number, or auto (null too): on a GPU one per CPU core of the process less one (at most
    # 16), on the CPU none (unicorn.lit.data.auto_num_workers)
    num_workers: Any = "auto"
    seed: int = 0
    val_size: int | None = ranged(None, 1)
    on_error: str = "raise"
    pin_memory: Any = "auto"  # true, false, or auto (null too): pinned when training on CUDA
    cache_items: bool = False
    synthetic: dict[str, Any] | None = None
    options: dict[str, Any] | None = None
    # images above this many pixels are bad images; null: $UNICORN_MAX_IMAGE_PIXELS or PIL's ~179M; 0: no limit
    max_image_pixels: int | None = ranged(None, 0)
    # images decoding to more bytes (float32 RGB: 12 per pixel) are bad images; null: $UNICORN_MAX_IMAGE_BYTES or
    # 1 GiB; 0: no limit
    max_image_bytes: int | None = ranged(None, 0)


# ---------------------------------------------------------------------------------------------- schedule
@dataclass
class CurriculumConfig:
    """Iteration at which each stage-1 switch turns on (0: from the start).

    ``translation``, ``deformation`` and ``scale`` are the paper's curriculum. ``elevation_roll`` is not in the
    paper (0 keeps its setting): until then every pose candidate keeps the elevation and roll of its anchor and
    regresses only its azimuth, so that early, up-down symmetric shapes are not placed seen from below by some
    candidates and from above by others when the elevation range allows both (the ``real`` family's).
    """

    translation: int = ranged(0, 0)
    deformation: int = ranged(0, 0)
    scale: int = ranged(0, 0)
    elevation_roll: int = ranged(0, 0)


@dataclass
class TextureAveragingConfig:
    """Mean-colour textures: constant during the first ``constant_stages`` stages (or, where ``constant_until`` is
    set, before that iteration, whatever the stage), then with probability ``p`` per batch while the stage is below
    ``random_until_stage`` (null: for the whole run)."""

    constant_stages: int = ranged(0, 0, N_STAGES)
    constant_until: int | None = ranged(None, 0)
    p: float = ranged(0.2, 0, 1)
    random_until_stage: int | None = ranged(N_STAGES, 1, N_STAGES)


@dataclass
class PlateauConfig:
    """Automatic stage changes: move on when the 3D-step reconstruction loss stops improving.

    Every ``check_every`` iterations the mean of the last ``window`` 3D-step reconstruction losses is
    compared with the mean of the ``window`` before; a relative improvement below ``threshold`` for
    ``patience`` checks in a row ends the stage, provided it lasted ``min_steps``.
    """

    window: int = ranged(2000, 1)
    check_every: int = ranged(1000, 1)
    threshold: float = ranged(0.01, 0)
    patience: int = ranged(3, 1)
    min_steps: int = ranged(10000, 0)


@dataclass
class ScheduleConfig:
    """Progressive conditioning, all in iterations (one iteration: one pose or one 3D step); the defaults are the
    paper's real-image design, 4 stages x 750k iterations."""

    mode: str = "fixed"  # SCHEDULE_MODES
    milestones: list[int] = field(default_factory=lambda: [750000, 1500000, 2250000])  # stages 2, 3 and 4 start
    alternation_period: int = ranged(1, 1)  # pose and 3D steps alternate every this many iterations
    # each training image's hue rotated by a random fraction of the hue circle in [-hue_shift, hue_shift], input and
    # target alike (unicorn.data.augment.random_hue_shift); 0: off, the paper's setting
    hue_shift: float = ranged(0.0, 0, 0.5)
    # each training image turned about its centre by up to roll_jitter degrees and moved by up to shift_jitter (NDC)
    # along x and y, input and target alike (unicorn.data.augment.random_roll_shift); 0: off, the paper's setting
    roll_jitter: float = ranged(0.0, 0, 90)
    shift_jitter: float = ranged(0.0, 0, 1)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    texture_averaging: TextureAveragingConfig = field(default_factory=TextureAveragingConfig)
    plateau: PlateauConfig = field(default_factory=PlateauConfig)


#: allowed values of the optimisation's string settings (see :class:`OptimConfig`)
OPTIM_CHOICES: dict[str, tuple[str, ...]] = {"idle_params": ("skip", "momentum"), "adam_state": ("shared", "per_step")}


@dataclass
class OptimConfig:
    """Adam over all parameters (the paper's learning rate 1e-4); see :mod:`unicorn.lit.module`.

    ``idle_params``: what the half of the parameters that a pose / 3D step does not reach does: ``skip`` (grad
    None, Adam leaves them alone) or ``momentum`` (zero grad, Adam moves them along their first moment, the
    reference's PyTorch-1.10 behaviour). ``adam_state``: ``shared`` (one Adam, the paper's) or ``per_step`` (one
    Adam per step kind: the shared encoder's 3D updates are then not scaled down by the pose step's larger
    gradients).
    """

    lr: float = 1e-4
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    eps: float = ranged(1e-8, 0)
    weight_decay: float = ranged(0.0, 0)
    lr_drop_step: int | None = None  # iteration at which the learning rate is multiplied by lr_drop_gamma
    lr_drop_gamma: float = ranged(0.2, 1e-6, 1)  # > 0: at 0 the run would go on without learning
    idle_params: str = "skip"
    check_finite: bool = True  # stop on a NaN / inf loss or gradient (after saving a checkpoint)
    # steps without host reads (unicorn.hostsync): null (default) on CUDA only; false: every step reads its inputs'
    # values and its finite flag (a debugging aid on CUDA); true: on the CPU too (to compare)
    sync_free: bool | None = None
    fused: bool = True  # torch's fused Adam kernel (same update up to rounding, several times faster on CPU)
    adam_state: str = "shared"
    texture_lr_scale: float = ranged(1.0, 1e-6)  # the texture branch's learning rate over lr (paper: 1)
    background_lr_scale: float = ranged(1.0, 1e-6)  # the background branch's learning rate over lr (paper: 1)


# ---------------------------------------------------------------------------------------------- run
@dataclass
class TrainerConfig:
    """Keyword arguments of :class:`lightning.pytorch.Trainer` that the configs may set."""

    accelerator: str = "auto"
    devices: Any = "auto"
    num_nodes: int = ranged(1, 1)
    strategy: Any = "auto"
    precision: Any = "32-true"
    max_steps: int = ranged(3000000, 1)  # training is counted in iterations
    val_check_interval: int | None = 2000  # validation every this many iterations (null: none)
    limit_val_batches: Any = 1.0
    num_sanity_val_steps: int = ranged(0, -1)
    log_every_n_steps: int = ranged(50, 1)
    enable_progress_bar: bool = True
    enable_model_summary: bool = True
    deterministic: Any = False
    benchmark: bool | None = None
    profiler: str | None = None
    sync_batchnorm: bool = False


@dataclass
class CheckpointConfig:
    """Periodic atomic checkpoints ``step=<N>.ckpt`` (the last ``keep`` kept) and ``last.ckpt``."""

    _target_: str = "unicorn.lit.callbacks.periodic_checkpoint"
    every_n_steps: int = ranged(10000, 1)
    keep: int = ranged(2, -1)  # -1: all
    save_last: bool = True


@dataclass
class ImagesConfig:
    """Image logging: inputs, reconstructions, the mesh from ``n_views`` azimuths, textures, backgrounds."""

    _target_: str = "unicorn.lit.ImageLogger"
    every_n_steps: int = ranged(2000, 1)  # (and after iteration 1)
    n_images: int = ranged(8, 1)
    n_views: int = ranged(4, 1)
    save_png: bool = True  # also <run>/images/step=N.png


#: the most Adam steps of a mean-shape fit (``mean_shape_iterations``; 300-3000 are typical)
MAX_MEAN_SHAPE_ITERATIONS = 100_000


@dataclass
class EvalSettings:
    """What an evaluation scores and how finely: the settings ``unicorn-eval``, the evaluation after training
    (:class:`EvaluateConfig`) and the held-out evaluation (:class:`HeldOutConfig`) share. The defaults are
    UNICORN's validation setting (:data:`FAST_EVAL`); ``unicorn-eval``'s (:class:`unicorn.evaluation.EvalOptions`)
    are its final protocol (:data:`FINAL_EVAL`)."""

    split: str = "test"
    max_images: int | None = ranged(None, 1)  # null: the whole split
    num_points: int = ranged(FAST_EVAL["num_points"], 1)  # points per mesh for Chamfer
    icp_iterations: int = ranged(FAST_EVAL["icp_iterations"], 0)  # 0: no -ICP metrics
    batch_size: int = ranged(EVAL_BATCH_SIZE, 1)
    # > 0: score each category's mean training shape beside the model (a fit of that many Adam steps)
    mean_shape_iterations: int = ranged(0, 0, MAX_MEAN_SHAPE_ITERATIONS)
    own_mean_shape: bool = False  # score the model's own average shape beside it (shape-win-own)
    shape_points: int = ranged(SHAPE_POINTS, 0)  # > 0: shape retrieval among the evaluated objects, points per shape


@dataclass
class HeldOutConfig(EvalSettings):
    """Held-out evaluation during training (:class:`unicorn.lit.HeldOutEvaluation`), rows in ``heldout.csv``:
    small enough to run inside training."""

    _target_: str = "unicorn.lit.HeldOutEvaluation"
    every_n_steps: int = ranged(1000, 1)
    split: str = "val"
    max_images: int = 32
    num_points: int = 5000
    icp_iterations: int = 20
    at_start: bool = True
    mean_shape_models: int = ranged(200, 1)
    shape_points: int = 1000


@dataclass
class DiagnosticsConfig:
    """Code spread and dead units of the code regressors (:class:`unicorn.lit.CodeDiagnostics`), rows in
    ``diagnostics.csv``, a loud warning when a branch collapses."""

    _target_: str = "unicorn.lit.CodeDiagnostics"
    every_n_steps: int = ranged(100, 1)
    max_images: int = ranged(64, 2)  # the most recent training images
    spread_tol: float = ranged(1e-6, 0)  # collapsed: a code whose active dimensions vary less across the images
    # collapsed: a shape code spread below this x the texture code's (one blob for every car: 0.01; trained cars,
    # tables and mugs whose shapes follow the image: 0.03-0.07)
    shape_spread_ratio: float = ranged(0.02, 0)
    # viewpoint learning collapsed (from stage 2 on): the pose branch's accuracy on renders of the model's own
    # reconstructions at drawn viewpoints below this (0: not judged), or one candidate the most likely for more
    # than share_max_tol of the images (1: not judged)
    viewpoint_acc_tol: float = ranged(0.5, 0, 1)
    share_max_tol: float = ranged(0.9, 0, 1)


@dataclass
class CallbacksConfig:
    """Every callback is a node built by its ``_target_``; null leaves it out (``heldout``: off by default, e.g.
    ``{every_n_steps: 1000, split: val, max_images: 32}``; its rows are the learning curves in ``heldout.csv``)."""

    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    images: ImagesConfig | None = field(default_factory=ImagesConfig)
    heldout: HeldOutConfig | None = None
    diagnostics: DiagnosticsConfig | None = field(default_factory=DiagnosticsConfig)
    progress_bar_refresh_rate: int = ranged(1, 0)
    extra: dict[str, Any] = field(default_factory=dict)  # name -> instantiable callback (``_target_``)


@dataclass
class EvaluateConfig(EvalSettings):
    """Evaluation of ``last.ckpt`` after training (``unicorn-eval``'s session), written to ``<run>/eval``; its mesh
    settings default to UNICORN's validation setting (:data:`FAST_EVAL`), not ``unicorn-eval``'s (:data:`FINAL_EVAL`,
    the paper's protocol)."""

    enabled: bool = False
    report_samples: int = ranged(REPORT_SAMPLES, 0)
    turntable_frames: int = ranged(REPORT_TURNTABLE_FRAMES, 0)  # 0: no turntables in the report


@dataclass
class PathsConfig:
    """Where runs and downloads go (``conf/paths/default.yaml`` sets the run's folder, the cache and the VGG16
    weights from Hydra and the environment)."""

    log_dir: str = "outputs"  # parent of every run directory (relative to the launch directory)
    output_dir: str = "outputs"
    cache_dir: str = "~/.cache/unicorn"
    vgg16: str | None = None


@dataclass
class TrainConfig:
    """A training run: the schema of ``conf/train.yaml`` and its groups (registered as :data:`SCHEMA_NAME`)."""

    task_name: str = "train"  # names the output folder: outputs/<task_name>/...
    seed: int = 0  # seeds weights, data order, texture-averaging draws
    ckpt_path: str | None = None  # resume: a checkpoint file, or "last" (this run directory's checkpoints/last.ckpt)
    # start a new run from the weights of a released .pkl, a save_model file or a .ckpt (iteration 0, fresh
    # optimizers; the model settings must match its architecture)
    init_from: str | None = None
    trust_checkpoint: bool = False  # read ckpt_path / init_from with full unpickling: it can run code (trusted files)
    overwrite: bool = False  # train in a folder holding an earlier run (not resumed): its checkpoints and logs go
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    renderer: dict[str, Any] = field(default_factory=dict)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: dict[str, Any] = field(default_factory=dict)  # name -> instantiable Lightning logger
    callbacks: CallbacksConfig = field(default_factory=CallbacksConfig)
    evaluate: EvaluateConfig = field(default_factory=EvaluateConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)


#: the schema's name in Hydra's ConfigStore: the first entry of ``conf/train.yaml``'s defaults list
SCHEMA_NAME = "train_schema"


def open_nodes(schema: type = TrainConfig, prefix: str = "") -> dict[str, frozenset[str] | None]:
    """The nodes whose keys a composed config may lack although the schema allows them: a group that may be null
    (``callbacks.heldout``, ``model.background``: a preset sets it null or names only some of its keys) with its
    keys, and a free mapping (``callbacks.extra``, ``dataset.synthetic``) with None (any key).

    The composed config holds plain values (:func:`store_schema`), so Hydra refuses ``callbacks.heldout.split=test``
    when the preset's ``callbacks.heldout`` names no ``split``; ``unicorn-train`` writes such overrides with ``++``
    (add or replace: :func:`unicorn.cli.train.hydra_argv`), and :func:`unicorn.config.validate` still checks them.
    """
    found: dict[str, frozenset[str] | None] = {}
    hints = typing.get_type_hints(schema)
    for item in dataclasses.fields(schema):
        hint, path = hints[item.name], f"{prefix}{item.name}"
        members = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
        kinds = [m for m in members if m is not type(None)]
        if len(kinds) == 1 and dataclasses.is_dataclass(kinds[0]):
            if len(members) > 1:  # may be null
                found[path] = frozenset(f.name for f in dataclasses.fields(kinds[0]))
            found.update(open_nodes(kinds[0], f"{path}."))
        elif any((typing.get_origin(kind) or kind) is dict for kind in kinds):
            found[path] = None
    return found


def store_schema() -> None:
    """Register :class:`TrainConfig`'s defaults in Hydra's ConfigStore as :data:`SCHEMA_NAME` (again: harmless).

    Stored as plain values rather than as the typed structured config: OmegaConf cannot merge a mapping given on
    the command line into an optional group whose typed value is null (``callbacks.heldout={every_n_steps: 1000}``,
    ``model.background={...}`` after the ShapeNet family; omegaconf issues 1035 and 1360). Hydra still refuses a
    key that is not there; :func:`unicorn.config.validate` merges the composed config onto the typed schema
    (types, keys added with ``+``) and checks the values.
    """
    ConfigStore.instance().store(name=SCHEMA_NAME, node=OmegaConf.to_container(OmegaConf.structured(TrainConfig)))


# on import, so that composing conf/train.yaml after importing unicorn.config works in any script (hydra.compose)
store_schema()
