"""The LightningModule that trains :class:`unicorn.model.Unicorn` with manual optimization.

Alternation. Iteration ``i`` (Lightning's ``global_step`` before the step) is a pose step when
``(i // alternation_period) % 2 == 0`` and a 3D step otherwise; the period is 1 in the paper (pose, 3D, pose,
...). Each iteration takes one batch and makes one optimizer step, so ``global_step`` counts iterations exactly
as the paper does, and ``trainer.max_steps`` and every milestone are in iterations.

One Adam over all parameters (lr 1e-4), with an optional drop of the learning rate at ``lr_drop_step`` (the
ShapeNet schedules multiply it by 0.2 for the last ~50k iterations). What the idle half of the parameters (the
3D branches in a pose step, the pose heads in a 3D step) does is ``optim.idle_params``:

- ``"skip"`` (default): gradients are reset with ``zero_grad(set_to_none=True)``; a parameter that the step's
  loss does not reach keeps ``grad = None`` and Adam skips it entirely: it does not move, and its moments and
  step count are untouched. Each half is then optimised by its own steps only (and the Adam bias correction
  counts those steps), which is what the alternation means.
- ``"momentum"``: the reference's behaviour under PyTorch 1.10, ``zero_grad(set_to_none=False)``: the idle half
  receives zero gradients and Adam still moves it along its decaying first moment at every step.

The shared encoder is reached by both steps and is updated at every iteration in both modes.

Adam's moments are ``optim.adam_state``:

- ``"shared"`` (the paper's and the reference's one Adam): both steps update one set of moments;
- ``"per_step"``: one Adam per step kind over the same parameters. A parameter that both steps reach (the
  shared encoder) then gets each step's update normalised by that step's own gradient scale. With one set of
  moments the pose step's larger encoder gradients set the second moment, and the 3D step's encoder updates
  shrink accordingly (what that does to the colours: ``docs/training.md``, "Optimiser options").

Stage state. The stage (1-4) and the texture-averaging probability are buffers of this module, and the code
sizes and stage-1 switches are buffers of the model, so a checkpoint alone restores them (the stage callback,
:class:`unicorn.lit.callbacks.StageCallback`, sets them). The neighbour memory bank and the random states are
written to the checkpoint by :meth:`on_save_checkpoint` (every rank's, see :mod:`unicorn.lit`) and restored
when training restarts, so a resumed run continues exactly.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import random
import warnings
from collections.abc import Callable, Mapping
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F

from unicorn.checks import NonFiniteValueError
from unicorn.config.build import ConfigError, check_optim
from unicorn.config.schema import OptimConfig
from unicorn.data.augment import random_hue_shift, random_roll_shift
from unicorn.hostsync import is_sync_free, sync_free
from unicorn.lit.compiled import CompiledStep
from unicorn.lit.finite import FiniteCheck, NonFiniteLossError
from unicorn.lit.loggers import logs_this_step
from unicorn.lit.overflow import TrainingOverflow
from unicorn.metrics import mask_iou
from unicorn.model import Unicorn
from unicorn.model.encoder import crop_optimizer_state
from unicorn.objectives import Objectives
from unicorn.render.overflow import counting
from unicorn.render.rasterizer import MeshRasterizer

__all__ = ["NonFiniteLossError", "OPTIM_DEFAULTS", "UnicornLitModule"]

log = logging.getLogger(__name__)

#: the optimisation settings' defaults (:class:`unicorn.config.schema.OptimConfig`, where each is documented)
OPTIM_DEFAULTS: dict[str, Any] = dataclasses.asdict(OptimConfig())
_SEED_STRIDE = 1_000_003
#: the texture-averaging draws are made for this many iterations at once (one host read of a host tensor)
_DRAWS = 256
#: ``optim.idle_params`` -> how gradients are reset before a step (``zero_grad(set_to_none=...)``)
_SET_TO_NONE = {"skip": True, "momentum": False}
#: ``optim.adam_state`` -> which of the Adams (their index) each step kind uses
_OPTIMIZER_OF_STEP = {"shared": {"pose": 0, "3d": 0}, "per_step": {"pose": 0, "3d": 1}}


def _to_device(values: dict[str, Any], device: torch.device | str) -> dict[str, Any]:
    """``values``' tensors detached and moved to ``device``; other values as they are."""
    return {k: v.detach().to(device) if isinstance(v, torch.Tensor) else v for k, v in values.items()}


def _rng_state() -> dict[str, Any]:
    # plain types and tensors only: Lightning loads checkpoints with torch.load(weights_only=True)
    name, keys, pos, has_gauss, gauss = np.random.get_state()  # noqa: NPY002 (the legacy global generator)
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(gauss)],
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))  # noqa: NPY002
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _check_resume_state(state: Any, where: str) -> None:
    """``checkpoint["unicorn"]`` as :meth:`UnicornLitModule.on_save_checkpoint` writes it (None: absent): one entry
    per rank with its neighbour memory (tensors or None) and random states, which are tried on scratch generators.

    Raises:
        unicorn.io.serialization.CheckpointError: the first field that differs, named (a checkpoint changed by hand
            or by another program: its hash was re-sealed or absent).
    """
    from unicorn.io.serialization import CheckpointError

    def refuse(field: str, what: str) -> CheckpointError:
        return CheckpointError(f"{where}: its resume state's {field} must be {what}")

    if state is None:
        return
    ranks = state.get("ranks") if isinstance(state, Mapping) else None
    if not isinstance(ranks, list) or not ranks:
        raise refuse("'unicorn' entry", "a dict whose 'ranks' is a non-empty list")
    for i, rank in enumerate(ranks):
        memory = rank.get("memory") if isinstance(rank, Mapping) else None
        if not isinstance(memory, Mapping) or any(v is not None and not torch.is_tensor(v) for v in memory.values()):
            raise refuse(f"ranks[{i}].memory", "a dict of tensors")
        rng = rank.get("rng")
        try:
            torch.Generator().set_state(rng["torch"])
            name, keys, pos, has_gauss, gauss = rng["numpy"]
            np.random.RandomState().set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
            random.Random().setstate(rng["python"])
        except Exception as err:  # noqa: BLE001 - each generator refuses a bad state in its own way
            raise refuse(f"ranks[{i}].rng", f"torch, numpy and python random states ({type(err).__name__})") from None


@functools.lru_cache(maxsize=4)
def _averaging_draws(base: int, chunk: int) -> tuple[float, ...]:
    """The texture-averaging draws of iterations ``chunk * _DRAWS`` to ``(chunk + 1) * _DRAWS - 1``: each the first
    ``torch.rand(())`` (float32) of a generator seeded with ``base`` plus the iteration."""
    first = chunk * _DRAWS
    draws = [torch.rand((), generator=torch.Generator().manual_seed(base + first + i)) for i in range(_DRAWS)]
    return tuple(torch.stack(draws).tolist())


class UnicornLitModule(L.LightningModule):
    """Trains UNICORN by alternating pose and 3D steps (see the module docstring).

    It owns the model (``self.model``, :class:`unicorn.model.Unicorn`) and the training objectives built from the
    model's ``loss`` group (``self.objectives``, :class:`unicorn.objectives.Objectives`, with the neighbour memory).

    Args:
        model: configuration of :class:`unicorn.model.Unicorn` (e.g. :func:`unicorn.config.model_config`).
        optim: Adam and learning-rate settings, over :data:`OPTIM_DEFAULTS` (``lr``, ``betas``, ``eps``,
            ``weight_decay``, ``lr_drop_step``, ``lr_drop_gamma``, ``idle_params``, ``check_finite``, ``fused``,
            ``adam_state``, ``texture_lr_scale`` and ``background_lr_scale``: those branches' learning rates over
            ``lr``; ``sync_free``: steps without host reads, :mod:`unicorn.lit.finite` and :mod:`unicorn.hostsync`).
        alternation_period: iterations per phase (1: pose and 3D steps alternate every iteration).
        hue_shift: each training image's hue is rotated by a random fraction of the hue circle in ``[-hue_shift,
            hue_shift]`` before both steps read it, as input and as target
            (:func:`unicorn.data.augment.random_hue_shift`); 0 (the paper's setting): images as they are.
        roll_jitter, shift_jitter: each training image is then turned about its centre by a random angle in
            ``[-roll_jitter, roll_jitter]`` degrees and moved by up to ``shift_jitter`` (NDC) along x and y, as input
            and as target (:func:`unicorn.data.augment.random_roll_shift`); 0 (the paper's setting): not moved.
        seed: seeds the per-batch texture-averaging, hue and jitter draws (pure functions of seed, iteration and
            rank).
    """

    stage: torch.Tensor
    texture_average_p: torch.Tensor

    def __init__(
        self,
        model: Mapping[str, Any],
        optim: Mapping[str, Any] | None = None,
        alternation_period: int = 1,
        hue_shift: float = 0.0,
        roll_jitter: float = 0.0,
        shift_jitter: float = 0.0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.automatic_optimization = False
        self.model = Unicorn(model)
        # the training objectives and their state (neighbour memory), built right after the model: the VGG
        # perceptual loss draws its (then overwritten) initial weights from the random stream the run continues
        self.objectives = Objectives.from_config(self.model.config["loss"], self.model)
        unknown = set(optim or {}) - set(OPTIM_DEFAULTS)
        if unknown:
            raise KeyError(f"unknown optim keys {sorted(unknown)}; known: {sorted(OPTIM_DEFAULTS)}")
        self.optim = {**OPTIM_DEFAULTS, **dict(optim or {})}
        check_optim(self.optim, prefix="")
        if self.model.background is None and float(self.optim["background_lr_scale"]) != 1.0:
            raise ConfigError(
                f"optim.background_lr_scale={self.optim['background_lr_scale']} but the model has no background "
                "branch (model.background is null)"
            )
        if alternation_period < 1:
            raise ValueError(f"alternation_period must be >= 1, got {alternation_period}")
        if not 0.0 <= hue_shift <= 0.5:
            raise ValueError(f"hue_shift must be in [0, 0.5] (a fraction of the hue circle), got {hue_shift}")
        if roll_jitter < 0 or shift_jitter < 0:
            raise ValueError(f"roll_jitter and shift_jitter must be >= 0, got {roll_jitter}, {shift_jitter}")
        self.alternation_period, self.hue_shift, self.seed = int(alternation_period), float(hue_shift), int(seed)
        self.roll_jitter, self.shift_jitter = float(roll_jitter), float(shift_jitter)
        # training state that must survive a checkpoint: buffers
        self.register_buffer("stage", torch.tensor(1, dtype=torch.long))
        self.register_buffer("texture_average_p", torch.tensor(0.0))
        self._resume_state: dict[str, Any] | None = None
        self.finite = FiniteCheck(self)
        #: steps without host reads (:mod:`unicorn.hostsync`; ``optim.sync_free``): None on CUDA only
        self.sync_free: bool | None = self.optim["sync_free"]
        #: the iterations of each process that check their inputs' values and read their flag before sync_free
        self.checked_steps = 2
        #: the texture-averaging probability as the stage callback last wrote it (read instead of the buffer)
        self.texture_average_host: float | None = None
        #: what the progress bar shows, on the host (a logged tensor would be read back at every iteration): the
        #: stage, from the stage callback, and the total loss, read where the step reads anyway
        self.progress: dict[str, float | int] = {}
        self._steps_run = 0
        self._unread: int | None = None  # the latest step without host reads, if no step has read since
        # the training renders' overflow where no other counter collects it (no diagnostics)
        self._overflow = TrainingOverflow(logged=False)
        #: the steps without host reads' forward compiled whole (``model.compile_scope=step``, :meth:`compile_step`)
        self.compiled_step: CompiledStep | None = None
        # each step kind's terms of its latest iteration, logged together (see training_step)
        self._latest_terms: dict[str, dict[str, torch.Tensor]] = {}

    # ------------------------------------------------------------------ schedule helpers
    def phase(self, step: int) -> str:
        """``"pose"`` or ``"3d"``: the kind of step iteration ``step`` (0-based) makes."""
        return "pose" if (step // self.alternation_period) % 2 == 0 else "3d"

    @property
    def constant_mean_textures(self) -> bool:
        """Whether the schedule currently renders mean-colour textures for every batch (p = 1)."""
        return float(self.texture_average_p) >= 1.0

    def average_texture(self, step: int) -> bool:
        """Whether iteration ``step`` renders mean-colour textures (constant, or drawn once per batch)."""
        p = self.texture_average_host if is_sync_free() else None
        if p is None:
            p = float(self.texture_average_p)  # a 0-dim read: the choice is a Python branch
        if p >= 1.0 or p <= 0.0:
            return p >= 1.0
        # the draw of torch.rand((), generator=...) (float32) seeded by the iteration, against p in float32
        return _averaging_draws(self.seed * _SEED_STRIDE, step // _DRAWS)[step % _DRAWS] < float(np.float32(p))

    def training_images(self, images: torch.Tensor, step: int) -> torch.Tensor:
        """The images iteration ``step`` trains on: (B, 3, S, S) hue-shifted when ``hue_shift`` > 0, then rolled and
        shifted when ``roll_jitter`` or ``shift_jitter`` > 0."""
        if self.hue_shift > 0.0:
            images = random_hue_shift(images, self.hue_shift, self._augment_generator(images, step, 1))
        if self.roll_jitter > 0.0 or self.shift_jitter > 0.0:
            generator = self._augment_generator(images, step, 2)
            images = random_roll_shift(images, self.roll_jitter, self.shift_jitter, generator)[0]
        return images

    def _augment_generator(self, images: torch.Tensor, step: int, stream: int) -> torch.Generator:
        """The generator of augmentation ``stream`` at iteration ``step``: its own (not the texture-averaging one),
        per rank (DDP ranks augment their own images), on the host (the same draws on every device), or on the
        images' device in the steps without host reads (a host draw would be copied there, a copy the host waits
        for)."""
        seed = np.random.SeedSequence([self.seed, step, self.global_rank, stream]).generate_state(1)[0]
        device = images.device if is_sync_free() else torch.device("cpu")
        return torch.Generator(device=device).manual_seed(int(seed))

    # ------------------------------------------------------------------ training
    def compile_step(self, mode: str = "default", backend: str | Callable[..., Any] | None = None) -> None:
        """Compile the forward of the steps without host reads whole (:class:`unicorn.lit.compiled.CompiledStep`):
        the networks, the renderer and the losses of each step kind as one graph, CUDA graphs with
        ``mode="reduce-overhead"`` on CUDA. The steps then run without host reads on every device after the checked
        first ones (``optim.sync_free`` null); the checked steps, validation and evaluation stay eager.

        Raises:
            ValueError: ``optim.sync_free`` is false: the compiled steps need the steps without host reads.
        """
        if self.sync_free is False:
            raise ValueError("a compiled step needs the steps without host reads: optim.sync_free is false")
        self.compiled_step = CompiledStep(self.objectives, self.model, mode, backend)

    def _sync_free_step(self) -> bool:
        """Whether this step runs without host reads (:attr:`sync_free`, after :attr:`checked_steps` checked ones)."""
        enabled = self.sync_free
        if enabled is None:
            enabled = self.device.type == "cuda" or self.compiled_step is not None
        return bool(enabled) and self._steps_run >= self.checked_steps

    def _verifies(self, step: int) -> bool:
        """Whether iteration ``step`` reads the deferred finite flag: a logging step or the last (a checkpoint's
        reads in :meth:`on_save_checkpoint`)."""
        trainer = self.trainer
        last = (trainer.max_steps or -1) > 0 and step + 1 >= trainer.max_steps  # -1: no limit
        return logs_this_step(trainer) or last

    def _logging_reads(self, step: int) -> None:
        """What the steps without host reads left on the device: the finite-loss flag, the sizes the rasterizers'
        fixed buffers needed (grown where too small), and the renders' overflow where the step counted it."""
        if self.optim["check_finite"]:
            self.finite.verify(step)
        self._read_overflow(step)
        for module in self.model.modules():
            if isinstance(module, MeshRasterizer):
                for line in module.grow_buffers():
                    log.warning("rasterizer buffers at iteration %d: %s", step, line)

    def _read_overflow(self, step: int) -> None:
        """Take the overflow the steps counted themselves (no diagnostics): the first that finds any warns."""
        if self._overflow.counter.counts:
            self._overflow.share(step)

    def read_deferred(self) -> None:
        """Make the reads the steps without host reads left for the next logging step now (the finite-loss flag, the
        rasterizers' needed sizes). Every checkpoint makes them first (:meth:`on_save_checkpoint`), whichever
        callback or signal writes it, so that none holds the weights of a non-finite step.

        Raises:
            NonFiniteLossError: a step since the last read was not finite (the state is rolled back and saved first).
        """
        if self._unread is not None:
            step, self._unread = self._unread, None
            self._logging_reads(step)

    def _step(self, images: torch.Tensor, step: int, deferred: bool) -> tuple[Any, Any, bool]:
        """Iteration ``step``'s forward, backward and optimizer step: (its losses, the optimizer, the averaging)."""
        images = self.training_images(images, step)
        phase = self.phase(step)
        average = self.average_texture(step)
        opt = self._optimizer(phase)
        opt.zero_grad(set_to_none=_SET_TO_NONE[self.optim["idle_params"]])
        check = self.optim["check_finite"]
        if check and deferred:
            self.finite.begin(step)
        elif check:
            self.finite.snapshot()
        if deferred and self.compiled_step is not None:
            losses = self.compiled_step(phase, images, average, step)
        else:
            try:
                losses = self.objectives(phase, self.model, images, average_texture=average, iteration=step)
            except NonFiniteValueError as err:  # the renderer's input checks: weights the last update blew up
                if not check or deferred:  # (the steps without host reads do not check inputs)
                    raise
                self.finite.stop(step, phase, f"the prediction: {err}")
        self.manual_backward(losses["total"])
        if check and deferred:
            self.finite.defer(losses, step)
        elif check:
            self.finite.now(losses, step, phase)
        opt.step()
        return losses, opt, average

    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        """One iteration: a pose or a 3D step on ``batch["image"]`` (B, 3, S, S); returns the detached terms."""
        step = self.global_step
        deferred = self._sync_free_step()
        self._steps_run += 1
        # where no other counter collects the renders' overflow (no diagnostics), the step counts it: a render's
        # own warning would read it back at once, and the steps without host reads take it with their other reads
        own_count = not counting()
        with sync_free(deferred), self._overflow.counting(step) if own_count else contextlib.nullcontext():
            losses, opt, average = self._step(batch["image"], step, deferred)
        schedulers = self.lr_schedulers()
        if not isinstance(schedulers, list):
            schedulers = [] if schedulers is None else [schedulers]
        # every scheduler steps every iteration, so that all optimizers share one learning-rate schedule
        first_of_several = step == 0 and len(schedulers) > 1
        with warnings.catch_warnings() if first_of_several else contextlib.nullcontext():
            if first_of_several:
                # one Adam per step kind: the 3D step's has not stepped yet at iteration 0, and torch warns that the
                # schedule's first value would be skipped, which is not so for MultiStepLR (it counts iterations).
                # Only here: changing the filters resets Python's once-per-location warning registry.
                warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler\.step\(\)` before")
            for scheduler in schedulers:
                scheduler.step()

        reads = not deferred or self._verifies(step)  # the steps without host reads read on these steps only
        self._unread = None if reads else step
        if deferred and reads:
            self._logging_reads(step)
        elif not deferred:
            self._read_overflow(step)
        terms = {name: value.detach() for name, value in losses.items()}
        self._latest_terms[self.phase(step)] = {**terms, **losses.stats}
        if reads:
            self.progress["loss"] = float(terms["total"])
        if not logs_this_step(self.trainer):
            return terms  # Lightning would drop these step values: skip the ~20 log calls (4 % of a CPU step)
        # every step kind's latest terms: with steps alternating and an even log_every_n_steps, every logged
        # iteration is of the same kind, and the other kind's terms would never reach the loggers
        for kind, latest in self._latest_terms.items():
            self.log_dict({f"train/{kind}/{k}": v for k, v in latest.items()}, on_step=True, on_epoch=False)
        self.log("train/lr", opt.param_groups[0]["lr"], on_step=True, on_epoch=False)
        self.log("train/average_texture", float(average), on_step=True, on_epoch=False)
        probs = losses.probs  # (K, B), detached: the batch's pose probabilities, whichever the step
        shares = F.one_hot(probs.argmax(0), probs.shape[0]).float().mean(0)
        for k in range(probs.shape[0]):
            self.log(f"pose/share_{k}", shares[k], on_step=True, on_epoch=False)
            self.log(f"pose/prob_{k}", probs[k].mean(), on_step=True, on_epoch=False)
        return terms

    # ------------------------------------------------------------------ validation
    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        """Reconstruction error (``val/rgb``) and, where the data has masks, the silhouette IoU (``val/mask_iou``)."""
        images = batch["image"]
        pred = self.model.predict(images, average_texture=float(self.texture_average_p) >= 1.0)
        rec, alpha = self.model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
        self.log("val/rgb", F.mse_loss(rec, images), prog_bar=False, batch_size=images.shape[0])
        if "mask" in batch and bool(batch.get("has_mask", torch.tensor(False)).all()):
            # the evaluation's definition (two empty masks score 1), not a second one
            self.log("val/mask_iou", mask_iou(alpha, batch["mask"]), batch_size=images.shape[0])

    # ------------------------------------------------------------------ optimizer
    @staticmethod
    def make_optimizer(params: Any, optim: Mapping[str, Any]) -> torch.optim.Adam:
        """The Adam of training for ``params`` with ``optim`` settings (over :data:`OPTIM_DEFAULTS`)."""
        o = {**OPTIM_DEFAULTS, **dict(optim)}
        # fused: one kernel per parameter group instead of ~10 element-wise passes per tensor (the unfused Adam
        # is 15 % of a CPU step of the tiny model); the same update up to float rounding
        return torch.optim.Adam(
            params,
            lr=o["lr"],
            betas=tuple(o["betas"]),
            eps=o["eps"],
            weight_decay=o["weight_decay"],
            fused=bool(o["fused"]),
        )

    def _optimizer(self, phase: str) -> Any:
        """The optimizer of a ``"pose"`` or ``"3d"`` step (the same one when ``adam_state`` is shared)."""
        opts = self.optimizers()
        opts = opts if isinstance(opts, list) else [opts]
        return opts[_OPTIMIZER_OF_STEP[self.optim["adam_state"]][phase]]

    def _param_groups(self, o: Mapping[str, Any]) -> Any:
        """Fresh parameter groups for one Adam: all parameters at ``lr``, except the texture and background
        branches at ``lr * texture_lr_scale`` and ``lr * background_lr_scale`` in their own groups where the scale
        is not 1 (fresh each call: an optimizer takes ownership of its group dicts)."""
        branches = {"texture": self.model.texture, "background": self.model.background}
        groups, taken = [], set()
        for name, module in branches.items():
            scale = float(o.get(f"{name}_lr_scale", 1.0))
            if module is None or scale == 1.0:
                continue
            params = list(module.parameters())
            taken |= {id(p) for p in params}
            groups.append({"params": params, "lr": o["lr"] * scale})
        if not groups:
            return self.model.parameters()
        return [{"params": [p for p in self.model.parameters() if id(p) not in taken]}, *groups]

    def configure_optimizers(self) -> Any:
        o = self.optim
        milestones = [] if o["lr_drop_step"] is None else [int(o["lr_drop_step"])]
        n = len(set(_OPTIMIZER_OF_STEP[o["adam_state"]].values()))  # per_step: [pose step's, 3D step's]
        configs = []
        for _ in range(n):
            opt = self.make_optimizer(self._param_groups(o), o)
            # stepped once per iteration in training_step (manual optimization never steps schedulers itself)
            scheduler = torch.optim.lr_scheduler.MultiStepLR(opt, milestones=milestones, gamma=o["lr_drop_gamma"])
            configs.append({"optimizer": opt, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}})
        return configs[0] if n == 1 else configs

    # ------------------------------------------------------------------ checkpoint state
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Add every rank's neighbour memory and random states (``checkpoint["unicorn"]``), after the reads the steps
        without host reads left (:meth:`read_deferred`: a non-finite step raises here, before anything is written).

        Raises:
            NonFiniteLossError: a step since the last read was not finite (the state is rolled back and saved first).
        """
        self.read_deferred()
        memory = {k: (None if v is None else v.detach().cpu()) for k, v in self.objectives.memory.state().items()}
        # each step kind's latest terms, logged at every logged iteration: a resumed run's first row has them all
        latest = {kind: _to_device(terms, "cpu") for kind, terms in self._latest_terms.items()}
        state = {"memory": memory, "rng": _rng_state(), "latest_terms": latest}
        ranks = [state]
        if self.trainer.world_size > 1 and torch.distributed.is_available() and torch.distributed.is_initialized():
            ranks = [None] * torch.distributed.get_world_size()
            torch.distributed.all_gather_object(ranks, state)
        checkpoint["unicorn"] = {"version": 1, "ranks": ranks}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Check that the checkpoint's weights fit this model (Lightning loads them strictly after this hook) and
        keep its neighbour memory and random states for :meth:`on_train_start`.

        Raises:
            unicorn.io.serialization.CheckpointError: weights of another model (``ckpt_path`` with other settings),
                or a resume state not as this class saves it.
        """
        from unicorn.io.checkpoints import check_weights_fit
        from unicorn.io.serialization import CheckpointError

        path = self._resumed_from()
        check_weights_fit(checkpoint.get("state_dict", {}), self.state_dict(), "ckpt_path", path)
        # applied in on_train_start: the random state must be set after everything that precedes training
        _check_resume_state(checkpoint.get("unicorn"), f"ckpt_path {path}")
        self._resume_state = checkpoint.get("unicorn")
        saved, own = (
            len(checkpoint.get("optimizer_states", [])),
            len(set(_OPTIMIZER_OF_STEP[self.optim["adam_state"]].values())),
        )
        if saved and saved != own:  # Lightning would load what it can pair, silently
            raise CheckpointError(
                f"ckpt_path {path} holds {saved} optimiser state(s) and this run has {own} "
                f"(optim.adam_state={self.optim['adam_state']}): resume with the run's optim.adam_state"
            )
        # Lightning loads the optimizer states after this hook: fit older checkpoints' whole-kernel moments
        groups = self._param_groups(self.optim)
        params = [p for g in groups for p in g["params"]] if isinstance(groups, list) else list(groups)
        if sum(crop_optimizer_state(self.model, params, s) for s in checkpoint.get("optimizer_states", [])):
            log.info("cropped the optimizer moments saved for whole layer-4 kernels (an older checkpoint)")

    def _resumed_from(self) -> str:
        """The checkpoint a resume loads, as errors name it."""
        path = getattr(self._trainer, "ckpt_path", None) if self._trainer is not None else None
        return str(path) if path else "the checkpoint"

    def on_train_start(self) -> None:
        state, self._resume_state = self._resume_state, None
        if not state:
            return
        ranks = state["ranks"]
        mine = ranks[self.global_rank % len(ranks)]
        memory = self.objectives.memory
        try:
            memory.load_state({k: (None if v is None else v.to(self.device)) for k, v in mine["memory"].items()})
        except (KeyError, ValueError, RuntimeError, IndexError) as err:  # tensors, but not a memory's layout
            from unicorn.io.serialization import CheckpointError

            raise CheckpointError(
                f"ckpt_path {self._resumed_from()}: its resume state's neighbour memory cannot be restored: {err}"
            ) from None
        _set_rng_state(mine["rng"])
        latest = mine.get("latest_terms", {})  # absent from older checkpoints
        self._latest_terms = {kind: _to_device(terms, self.device) for kind, terms in latest.items()}
        log.info("restored the neighbour memory (%d entries) and random states", len(memory))
