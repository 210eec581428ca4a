"""Training callbacks: the progressive-conditioning stage schedule and image logging.

:class:`StageCallback` drives UNICORN's four stages. Before every iteration it computes, for the iteration
about to run (``trainer.global_step``), the stage, the stage-1 curriculum switches and the texture-averaging
mode, and writes them into the module's state (``UnicornLitModule.stage`` / ``texture_average_p`` and the
model's code-size and switch buffers): a checkpoint alone restores them, every DDP rank computes the same
values without communication, and a resumed run continues where it stopped. With fixed milestones the stage is
a pure function of the iteration; the ``plateau`` mode moves on when the 3D-step reconstruction loss stops
improving (decided on rank 0, broadcast to the others, bookkeeping saved with the callback's state). The plateau
mode keeps the losses on the device and the stage on the host between its checks: it reads the device on the check
iterations only (and when a checkpoint saves its state).

The neighbour loss needs active shape and texture codes, so with the paper's code sizes (no shape code in
stage 1) it starts with stage 2.

:class:`ImageLogger` renders, every N iterations, the inputs, their reconstructions, the predicted meshes from
several viewpoints, the textures and the backgrounds, to TensorBoard and as PNG files.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
from collections import deque
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_only

from unicorn.config.schema import (
    N_STAGES,
    SCHEDULE_MODES,
    CurriculumConfig,
    ImagesConfig,
    PlateauConfig,
    TextureAveragingConfig,
)
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.lit.checkpoint import PeriodicCheckpoint
from unicorn.lit.loggers import TensorBoardLogger as UnicornTensorBoardLogger
from unicorn.lit.loggers import logs_this_step

__all__ = ["ImageLogger", "ProgressBar", "StageCallback", "StageState", "periodic_checkpoint", "render_overview"]

log = logging.getLogger(__name__)

_SWITCHES = tuple(f.name for f in dataclasses.fields(CurriculumConfig))
#: the 3D-step terms whose sum the plateau mode watches
_RECONSTRUCTION = ("rgb", "perceptual")


class StageState(dict):
    """What the schedule prescribes for one iteration: ``stage``, ``dims`` (per code), ``switches`` (curriculum),
    ``texture_p`` (1: constant mean-colour textures, 0 < p < 1: averaged with probability p per batch)."""


class StageCallback(L.Callback):
    """Progressive conditioning, stage-1 curriculum and texture averaging (see the module docstring).

    Args:
        dims: active code sizes per stage, ``{"shape": [0, 2, 8, 32], "texture": [...], "background": [...]}``.
        milestones: iterations at which stages 2, 3 and 4 start (``fixed`` mode).
        curriculum: iteration at which each switch of :class:`CurriculumConfig` turns on.
        texture_averaging: ``constant_stages`` (constant mean-colour textures during the first stages) or
            ``constant_until`` (before that iteration, whatever the stage; None: by stages), ``p`` and
            ``random_until_stage`` (averaging with probability p per batch while the stage is below it; None: for
            the whole run).
        mode: ``"fixed"`` (milestones) or ``"plateau"``.
        plateau: ``window``, ``check_every``, ``threshold``, ``patience``, ``min_steps`` (see
            :class:`unicorn.config.schema.PlateauConfig`).
    """

    def __init__(
        self,
        dims: Mapping[str, Sequence[int]],
        milestones: Sequence[int],
        curriculum: Mapping[str, int] | None = None,
        texture_averaging: Mapping[str, Any] | None = None,
        mode: str = "fixed",
        plateau: Mapping[str, Any] | None = None,
    ) -> None:
        if mode not in SCHEDULE_MODES:
            raise ValueError(f"mode must be one of {SCHEDULE_MODES}, got {mode!r}")
        if len(milestones) != N_STAGES - 1 or list(milestones) != sorted(milestones):
            raise ValueError(f"need {N_STAGES - 1} increasing milestones, got {list(milestones)}")
        for name, values in dims.items():
            if values is not None and len(values) != N_STAGES:
                raise ValueError(f"dims[{name!r}] needs {N_STAGES} sizes, got {list(values)}")
        self.dims = {k: [int(d) for d in v] for k, v in dims.items() if v is not None}
        self.milestones = [int(m) for m in milestones]
        self.curriculum = {k: 0 for k in _SWITCHES} | {k: int(v) for k, v in dict(curriculum or {}).items()}
        self.texture_averaging = dataclasses.asdict(TextureAveragingConfig()) | dict(texture_averaging or {})
        self.mode = mode
        self.plateau = dataclasses.asdict(PlateauConfig()) | dict(plateau or {})
        # plateau bookkeeping (saved in the checkpoint)
        self._history: deque[float] = deque(maxlen=2 * int(self.plateau["window"]))
        # the 3D steps' terms since the last check, kept on the device
        self._pending: deque[torch.Tensor] = deque(maxlen=self._history.maxlen)
        self._strikes = 0
        self._stage_start = 0
        self._stage: int | None = None  # the plateau mode's stage: the module's buffer, read once per fit
        self._last: StageState | None = None

    @classmethod
    def from_config(cls, schedule: Any, model: Any) -> StageCallback:
        """The callback of a validated training config's ``schedule`` and ``model`` groups (the stages' code sizes;
        a model without background has no background sizes)."""
        from omegaconf import OmegaConf

        def plain(node: Any) -> Any:
            return OmegaConf.to_container(node, resolve=True)

        dims = plain(model.stages)
        if model.background is None:
            dims.pop("background")
        return cls(
            dims=dims,
            milestones=list(schedule.milestones),
            curriculum=plain(schedule.curriculum),
            texture_averaging=plain(schedule.texture_averaging),
            mode=schedule.mode,
            plateau=plain(schedule.plateau),
        )

    # ------------------------------------------------------------------ the schedule
    def fixed_stage(self, step: int) -> int:
        """Stage (1-4) of iteration ``step`` with the fixed milestones."""
        return 1 + bisect.bisect_right(self.milestones, step)

    def state_at(self, step: int, stage: int) -> StageState:
        """The settings of iteration ``step`` in ``stage``."""
        ta = self.texture_averaging
        until = ta["constant_until"]
        if (step < until) if until is not None else (stage <= ta["constant_stages"]):
            texture_p = 1.0
        elif ta["random_until_stage"] is None or stage < ta["random_until_stage"]:
            texture_p = float(ta["p"])
        else:
            texture_p = 0.0
        return StageState(
            stage=stage,
            dims={name: values[stage - 1] for name, values in self.dims.items()},
            switches={name: step >= self.curriculum[name] for name in _SWITCHES},
            texture_p=texture_p,
        )

    def apply(self, pl_module: L.LightningModule, state: StageState) -> None:
        """Write ``state`` into the module (stage and texture buffers) and its model (code sizes, switches)."""
        pl_module.stage.fill_(state["stage"])
        pl_module.texture_average_p.fill_(state["texture_p"])
        pl_module.texture_average_host = float(state["texture_p"])  # read by the steps without host reads
        pl_module.model.set_active_dims(**state["dims"])
        pl_module.model.set_stage_switches(**state["switches"])

    def _current(self, trainer: L.Trainer, pl_module: L.LightningModule) -> StageState:
        step = trainer.global_step
        stage = self.fixed_stage(step) if self.mode == "fixed" else self._plateau_stage(pl_module)
        return self.state_at(step, stage)

    def _plateau_stage(self, pl_module: L.LightningModule) -> int:
        if self._stage is None:
            self._stage = int(pl_module.stage)  # one read per fit: on_train_start resets it
        return self._stage

    def _describe(self, old: StageState | None, new: StageState, step: int) -> list[str]:
        lines = []
        if old is None or old["stage"] != new["stage"]:
            dims = ", ".join(f"{k} {v}" for k, v in new["dims"].items())
            prev = "start" if old is None else f"stage {old['stage']}"
            lines.append(f"iteration {step}: {prev} -> stage {new['stage']} (code sizes: {dims})")
        for name in _SWITCHES:
            if (old is None and not new["switches"][name]) or (
                old is not None and old["switches"][name] != new["switches"][name]
            ):
                lines.append(f"iteration {step}: {name} {'on' if new['switches'][name] else 'held off'}")
        if old is None or old["texture_p"] != new["texture_p"]:
            p = new["texture_p"]
            what = (
                "constant mean-colour textures"
                if p >= 1
                else (f"mean-colour textures with p={p:g}" if p > 0 else "full textures")
            )
            lines.append(f"iteration {step}: {what}")
        return lines

    # ------------------------------------------------------------------ hooks
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last, self._stage = None, None  # a resumed run's stage is the checkpoint's buffer
        self._update(trainer, pl_module)

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        state = self._update(trainer, pl_module)
        pl_module.progress["stage"] = state["stage"]
        if not logs_this_step(trainer):
            return  # Lightning would drop the step values below (their log calls cost 2 % of a CPU step)
        pl_module.log("stage", float(state["stage"]), on_step=True, on_epoch=False)
        for name, value in state["dims"].items():
            pl_module.log(f"stage/dims_{name}", float(value), on_step=True, on_epoch=False)
        for name, value in state["switches"].items():
            pl_module.log(f"stage/{name}", float(value), on_step=True, on_epoch=False)
        pl_module.log("stage/texture_p", state["texture_p"], on_step=True, on_epoch=False)
        loss = pl_module.model.config["loss"]
        neighbor = loss["neighbor_weight"] > 0 and state["dims"].get("shape", 1) > 0 and state["dims"]["texture"] > 0
        pl_module.log("stage/neighbor", float(neighbor), on_step=True, on_epoch=False)

    def _update(self, trainer: L.Trainer, pl_module: L.LightningModule) -> StageState:
        state = self._current(trainer, pl_module)
        for line in self._describe(self._last, state, trainer.global_step):
            if trainer.is_global_zero:
                log.info(line)
        if state != self._last:  # written when it changes: a few kernels fewer at every iteration
            self.apply(pl_module, state)
        self._last = state
        return state

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        if self.mode != "plateau" or not isinstance(outputs, Mapping):
            return
        if pl_module.phase(trainer.global_step - 1) == "3d":  # the iteration that just ran
            terms = [outputs[name] for name in _RECONSTRUCTION if name in outputs]
            if terms:
                self._pending.append(torch.stack(terms).detach())  # read at the next check, not now
        if trainer.global_step % int(self.plateau["check_every"]) != 0:
            return
        self._read_pending()
        stage = self._plateau_stage(pl_module)
        advance = torch.tensor(float(self._plateau_reached(stage, trainer.global_step)))
        advance = trainer.strategy.broadcast(advance, src=0)
        if float(advance) > 0:
            self._stage = stage + 1
            pl_module.stage.fill_(self._stage)
            self._stage_start, self._strikes = trainer.global_step, 0
            self._history.clear()

    def _read_pending(self) -> None:
        """Move the losses kept on the device into the history: one read for all of them."""
        if self._pending:
            self._history.extend(torch.stack(tuple(self._pending)).double().sum(1).tolist())
            self._pending.clear()

    def _plateau_reached(self, stage: int, step: int) -> bool:
        window = int(self.plateau["window"])
        if stage >= N_STAGES or step - self._stage_start < self.plateau["min_steps"] or len(self._history) < 2 * window:
            return False
        values = np.asarray(self._history)
        before, now = values[:window].mean(), values[window:].mean()
        improvement = (before - now) / max(abs(before), 1e-12)
        self._strikes = self._strikes + 1 if improvement < self.plateau["threshold"] else 0
        return self._strikes >= self.plateau["patience"]

    def state_dict(self) -> dict[str, Any]:
        self._read_pending()
        return {
            "milestones": self.milestones,
            "mode": self.mode,
            "history": list(self._history),
            "strikes": self._strikes,
            "stage_start": self._stage_start,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if state_dict.get("milestones") != self.milestones or state_dict.get("mode") != self.mode:
            log.warning(
                "resuming with a different stage schedule (checkpoint: %s %s, now: %s %s)",
                state_dict.get("mode"),
                state_dict.get("milestones"),
                self.mode,
                self.milestones,
            )
        self._history.clear()
        self._pending.clear()
        self._history.extend(state_dict.get("history", []))
        self._strikes = int(state_dict.get("strikes", 0))
        self._stage_start = int(state_dict.get("stage_start", 0))


# ---------------------------------------------------------------------------------------------- images
@torch.no_grad()
def render_overview(
    model: torch.nn.Module, images: torch.Tensor, n_views: int = 4, average_texture: bool = False
) -> torch.Tensor:
    """One row per image: input, reconstruction, the mesh from ``n_views`` azimuths, texture, background.

    Args:
        model: a :class:`unicorn.model.Unicorn` (put in eval mode by the caller).
        images: (N, 3, S, S) in [0, 1].

    Returns:
        (3, N * S, C * S) image grid in [0, 1].
    """
    pred = model.predict(images, average_texture=average_texture)
    rec, _ = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    n, size = images.shape[0], images.shape[-1]
    columns = [images, rec]
    elev = torch.full((n,), 20.0, device=images.device)
    T = images.new_tensor(model.config["pose"]["prior_translation"]).expand(n, 3)
    for v in range(n_views):
        azim = torch.full((n,), 360.0 * v / n_views + 30.0, device=images.device)
        R = azim_elev_roll_to_rotation(azim, elev)
        view, _ = model.render(pred.verts, pred.texture, R, T)
        columns.append(view)
    columns.append(F.interpolate(pred.texture, size=(size, size), mode="bilinear", align_corners=False))
    if pred.background is not None:
        columns.append(pred.background)
    rows = torch.cat(columns, dim=3)  # (N, 3, S, C * S)
    return rows.permute(1, 0, 2, 3).reshape(3, n * size, -1).clamp(0, 1)


def overview_labels(n_views: int, background: bool) -> list[str]:
    """The column headers of :func:`render_overview`'s grid (the mesh views by their azimuth in degrees)."""
    views = [f"az {360 * v // n_views + 30}" for v in range(n_views)]
    return ["input", "recon.", *views, "texture", *(["backgr."] if background else [])]


def save_overview(grid: torch.Tensor, size: int, labels: Sequence[str], path: str | Path) -> None:
    """Write :func:`render_overview`'s ``grid`` (3, N * size, C * size) as a PNG with a header naming its columns,
    each cell shown at 64 pixels or more (nearest neighbour), so that the headers fit."""
    from unicorn.evaluation.pictures import image_grid, to_uint8

    scale = max(1, -(-64 // size))
    array = to_uint8(grid.cpu())  # (N * size, C * size, 3)
    cells = [
        [array[r : r + size, c : c + size].repeat(scale, 0).repeat(scale, 1) for c in range(0, array.shape[1], size)]
        for r in range(0, array.shape[0], size)
    ]
    image_grid(cells, labels, pad=2).save(path)


class ImageLogger(L.Callback):
    """Logs :func:`render_overview` of the first ``n_images`` of the batch every ``every_n_steps`` iterations
    (and after the first one) to TensorBoard (``images/overview``) and as ``<run>/images/step=N.png``.

    Args:
        every_n_steps: logging period in iterations.
        n_images: rows (images of the current batch).
        n_views: viewpoints of the mesh.
        save_png: also write PNG files into ``<default_root_dir>/images``.
    """

    def __init__(
        self,
        every_n_steps: int = ImagesConfig.every_n_steps,
        n_images: int = ImagesConfig.n_images,
        n_views: int = ImagesConfig.n_views,
        save_png: bool = ImagesConfig.save_png,
    ) -> None:
        self.every_n_steps, self.n_images, self.n_views, self.save_png = every_n_steps, n_images, n_views, save_png

    @rank_zero_only
    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        step = trainer.global_step
        if step != 1 and step % self.every_n_steps != 0:
            return
        images = batch["image"][: self.n_images]
        was_training = pl_module.training
        pl_module.eval()  # batch-norm statistics must not see these renders
        try:
            grid = render_overview(pl_module.model, images, self.n_views, pl_module.constant_mean_textures)
        finally:
            pl_module.train(was_training)
        for logger in trainer.loggers:
            if isinstance(logger, UnicornTensorBoardLogger):  # whose failures do not end the run
                logger.log_image("images/overview", grid.cpu(), step)
            elif isinstance(logger, TensorBoardLogger):
                logger.experiment.add_image("images/overview", grid.cpu(), step)
        if self.save_png:
            folder = Path(trainer.default_root_dir) / "images"
            folder.mkdir(parents=True, exist_ok=True)
            labels = overview_labels(self.n_views, pl_module.model.background is not None)
            save_overview(grid, images.shape[-1], labels, folder / f"step={step:07d}.png")


def periodic_checkpoint(dirpath: str | Path, every_n_steps: int, keep: int, save_last: bool) -> PeriodicCheckpoint:
    """The run's checkpoints (``callbacks.checkpoint``): ``step=<N>.ckpt`` every ``every_n_steps`` iterations, the
    ``keep`` latest kept (-1: all; ``"step"`` is always a monitor candidate), and ``last.ckpt`` with ``save_last``."""
    return PeriodicCheckpoint(
        dirpath=dirpath,
        filename="step={step:07d}",
        auto_insert_metric_name=False,
        every_n_train_steps=every_n_steps,
        monitor="step",
        mode="max",
        save_top_k=keep,
        save_last=save_last,
    )


class ProgressBar(TQDMProgressBar):
    """Lightning's progress bar for an iteration-based run: no epoch label; the stage and the latest loss read from
    the module (``progress``)."""

    def on_train_epoch_start(self, trainer: L.Trainer, *args: Any) -> None:
        super().on_train_epoch_start(trainer, *args)
        self.train_progress_bar.set_description("Training")

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, int | str | float | dict]:
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        # the module's host values (UnicornLitModule.progress), not logged tensors: Lightning reads every logged
        # progress-bar tensor back at every iteration, a wait for the device
        items.update(getattr(pl_module, "progress", {}))
        return items
