"""Held-out evaluation during training: the metrics of :mod:`unicorn.evaluation` against the iteration.

:class:`HeldOutEvaluation` scores the model every N iterations (and once before the first one) on a fixed set
of held-out images with the dataset's evaluation protocol, at a cost small enough to run inside training
(few surface points, few ICP iterations). The numbers go to every logger under ``heldout/<metric>`` and, one
row per evaluation, to ``<run>/heldout.csv``: the learning curves of shape, silhouette and pose quality, not
only of the training loss. Nothing is selected on them: they are for watching and plotting.

They include the instance-level metrics of :func:`~unicorn.evaluation.evaluate`: the colour error beside the
mean-colour predictor's (``color-err``, ``color-err-mean``, ``color-ratio``), the flip rate (``rot-flip-150``)
and, with ``mean_shape_iterations`` > 0 on a dataset with ground-truth point clouds, each category's mean training
shape (fitted once, at the start) scored on its objects (``chamfer-L1-ICP-mean-shape``) and the share of
objects on which the model is closer (``shape-win``); with ``own_mean_shape``, the model's own average shape
over the held-out images scored the same way (``chamfer-L1-ICP-own-mean``, ``shape-win-own``): whether the
per-image shapes follow the objects, whatever the accuracy of the category's shape; and with ``shape_points`` > 0
the shape retrieval among the held-out objects (``shape-top1``, ``shape-top3``, ``shape-mrr``, their ``-gt``
ceiling and ``-floor``, ``shape-spread-ratio``, ``shape-detail-ratio``).
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_only

from unicorn.config.schema import HELDOUT_SPLITS, HeldOutConfig
from unicorn.lit.loggers import log_step
from unicorn.model.ranges import check_ranges

__all__ = ["HeldOutEvaluation", "append_csv_row"]

log = logging.getLogger(__name__)


class HeldOutEvaluation(L.Callback):
    """Evaluate on held-out images every ``every_n_steps`` iterations (see the module docstring).

    The images are the first ``max_images`` items (spread over the split) of
    :func:`~unicorn.evaluation.build_eval_dataset` for the training data's dataset and ``split``; the model is
    put in eval mode, and the global random state is left untouched, so a run with this callback trains
    exactly as one without it.

    Args:
        every_n_steps: evaluation period in iterations.
        split: ``"val"`` or ``"test"``.
        max_images: held-out images scored each time.
        num_points: surface points sampled per mesh for the Chamfer distances.
        icp_iterations: ICP iterations of the ``-ICP`` metrics (0: no ICP metrics).
        batch_size: images per forward pass.
        at_start: also evaluate before the first iteration (the untrained model, the start of the curves).
        filename: the CSV file, relative to the run directory.
        mean_shape_iterations: fit each category's mean shape to (at most ``mean_shape_models`` of) its training
            point clouds with this many iterations (:func:`~unicorn.evaluation.mean_shape.fit_mean_shapes`) and
            score it beside the model on the category's objects; 0: no shape baseline. Needs a dataset with point
            clouds (ShapeNet-NMR, synthetic) and ``icp_iterations`` > 0 (without ICP it is not fitted, with a log
            line).
        mean_shape_models: most training shapes of a category its mean shape is fitted to.
        own_mean_shape: also score the model's own average shape (``EvalOptions.own_mean_shape``).
        shape_points: points per shape of the shape retrieval (``EvalOptions.shape_points``); 0: off.
        progress: a progress bar while scoring (erased when done; a line is logged before and after either way).
    """

    def __init__(
        self,
        every_n_steps: int = HeldOutConfig.every_n_steps,
        split: str = HeldOutConfig.split,
        max_images: int = HeldOutConfig.max_images,
        num_points: int = HeldOutConfig.num_points,
        icp_iterations: int = HeldOutConfig.icp_iterations,
        batch_size: int = HeldOutConfig.batch_size,
        at_start: bool = HeldOutConfig.at_start,
        filename: str = "heldout.csv",
        mean_shape_iterations: int = HeldOutConfig.mean_shape_iterations,
        mean_shape_models: int = HeldOutConfig.mean_shape_models,
        own_mean_shape: bool = HeldOutConfig.own_mean_shape,
        shape_points: int = HeldOutConfig.shape_points,
        progress: bool = True,
    ) -> None:
        if split not in HELDOUT_SPLITS:
            raise ValueError(f"split must be one of {HELDOUT_SPLITS}, got {split!r}")
        check_ranges(locals(), HeldOutConfig)
        self.every_n_steps, self.split, self.max_images = int(every_n_steps), split, int(max_images)
        self.num_points, self.icp_iterations, self.batch_size = int(num_points), int(icp_iterations), int(batch_size)
        self.at_start, self.filename, self.progress = bool(at_start), filename, bool(progress)
        self.mean_shape_iterations, self.mean_shape_models = int(mean_shape_iterations), int(mean_shape_models)
        # category (evaluation group) -> its mean shape (V, 3), fitted with the dataset
        self.mean_shapes: dict[str, torch.Tensor] | None = None
        self.own_mean_shape, self.shape_points = bool(own_mean_shape), int(shape_points)
        self._dataset: Any = None
        self._name = "dataset"
        self.history: list[dict[str, float]] = []

    # ------------------------------------------------------------------ data
    def _build_dataset(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        from unicorn.evaluation import build_eval_dataset, get_protocol, protocol_for

        data = trainer.datamodule
        if data is None or not hasattr(data, "name"):
            raise RuntimeError("HeldOutEvaluation needs the run's UnicornDataModule (trainer.datamodule)")
        root = data.dataset_root() if hasattr(data, "dataset_root") else data.root
        self._name = data.name
        self._dataset = build_eval_dataset(
            data.name,
            str(root),
            self.split,
            img_size=pl_module.model.config["image_size"],
            categories=data.categories,
            max_images=self.max_images,
            options=getattr(data, "options", None),  # the dataset options naming the data (LSUN's tag)
        )
        clouds_known = get_protocol(protocol_for(data.name)).training_clouds
        if self.mean_shape_iterations > 0 and clouds_known and self.icp_iterations == 0:
            log.info("held-out: no mean shape is fitted: it is scored after ICP, and icp_iterations is 0")
        elif self.mean_shape_iterations > 0 and clouds_known:
            from unicorn.evaluation.baselines import category_point_clouds
            from unicorn.evaluation.mean_shape import fit_mean_shapes

            clouds = category_point_clouds(root, data.categories, self.mean_shape_models, num_points=self.num_points)
            template = pl_module.model.template
            with torch.random.fork_rng(devices=[]):  # the fit is seeded; leave the training's streams alone
                self.mean_shapes = fit_mean_shapes(
                    template.verts.detach(),
                    template.faces,
                    clouds,
                    iterations=self.mean_shape_iterations,
                    should_stop=lambda: _stop_signalled(trainer),
                )
            if self.mean_shapes is None:
                log.info("held-out: the mean-shape fit stopped by a signal: no mean shape is scored")
                return
            log.info(
                "held-out: each category's mean shape fitted to its training shapes (%s; %d iterations each)",
                ", ".join(f"{group} {len(group_clouds)}" for group, group_clouds in clouds.items()),
                self.mean_shape_iterations,
            )

    # ------------------------------------------------------------------ hooks
    @rank_zero_only
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._build_dataset(trainer, pl_module)
        if self.at_start and trainer.global_step == 0 and not _stop_signalled(trainer):
            self.evaluate_now(trainer, pl_module)

    @rank_zero_only
    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        if trainer.global_step % self.every_n_steps == 0:
            self.evaluate_now(trainer, pl_module)

    def evaluate_now(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, float]:
        """Score the current model, log and append the row; returns ``{"step": ..., metric: value}``."""
        from unicorn.evaluation import evaluate
        from unicorn.evaluation.session import settings_options

        if self._dataset is None:
            self._build_dataset(trainer, pl_module)
        options = settings_options(
            self,  # the held-out settings, as attributes
            self._name,
            average_texture=pl_module.constant_mean_textures,
            report_samples=0,
            progress=self.progress,
            progress_label=f"held-out {self.split}",
            progress_leave=False,
        )
        step = int(trainer.global_step)
        log.info("held-out %s: scoring %d images at iteration %d", self.split, len(self._dataset), step)
        was_training = pl_module.training
        devices = [pl_module.device] if pl_module.device.type == "cuda" else []
        # the evaluation draws points and ICP noise: keep the training's random streams where they were
        with torch.random.fork_rng(devices=devices):
            try:
                result = evaluate(
                    pl_module.model,
                    self._dataset,
                    options,
                    self._name,
                    device=pl_module.device,
                    shape_baseline=self.mean_shapes,
                )
            finally:
                pl_module.train(was_training)
        row = {"step": step, **{k: float(v) for k, v in result.mean.items() if k in result.columns}}
        self.history.append(row)
        metrics = {f"heldout/{k}": v for k, v in row.items() if k != "step" and math.isfinite(v)}
        for logger in trainer.loggers:
            logger.log_metrics(metrics, step=log_step(step))  # beside the iteration's training values
        self._append_csv(Path(trainer.default_root_dir) / self.filename, row)
        shown = ", ".join(f"{k} {v:.4g}" for k, v in row.items() if k != "step")
        log.info("held-out %s (%d images) at iteration %d: %s", self.split, len(self._dataset), step, shown)
        return row

    @staticmethod
    def _append_csv(path: Path, row: dict[str, float]) -> None:
        append_csv_row(path, row)


def append_csv_row(path: Path, row: dict[str, float]) -> None:
    """Add ``row`` (with a ``step``, a whole number) to a CSV file of one row per step, atomically; new columns
    widen the file. Steps are written as integers (``4``), also those of rows written as floats (``4.0``).

    The rows of ``row``'s step and later ones are dropped first: a resumed run writes again from its checkpoint's
    step on, so the file reads like that of a run never interrupted, also after a resume from an earlier
    checkpoint (whose abandoned later rows would otherwise stay)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    step = _whole_step(row["step"])
    rows: list[dict[str, Any]] = []
    if path.exists():
        with path.open(newline="", encoding="utf-8") as f:
            rows = [{**r, "step": _whole_step(r["step"])} for r in csv.DictReader(f)]
        rows = [r for r in rows if r["step"] < step]
    rows.append({**row, "step": step})
    columns = list(dict.fromkeys(k for r in rows for k in r))
    from unicorn.io.serialization import replacing

    with replacing(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)


def _whole_step(value: float | str) -> int:
    """An iteration as an integer, from a number or a CSV cell (``4``, ``4.0``)."""
    step = float(value)
    if not step.is_integer():
        raise ValueError(f"a step must be a whole number of iterations, got {value!r}")
    return int(step)


def _stop_signalled(trainer: L.Trainer) -> bool:
    """Whether a SIGTERM or SIGINT asked the run to stop (its :class:`~unicorn.lit.signals.GracefulStop`): the
    set-up's long parts (the mean-shape fit, the first scoring) give way, so that the run stops within seconds."""
    from unicorn.lit.signals import GracefulStop

    return any(isinstance(c, GracefulStop) and c.received is not None for c in trainer.callbacks)
