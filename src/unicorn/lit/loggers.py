"""Metric logs that survive a resume: the CSV is appended to, not rewritten, and neither log repeats iterations.

Lightning's :class:`~lightning.pytorch.loggers.CSVLogger` deletes ``metrics.csv`` when its folder exists, so
resuming a run in its own folder (the SLURM requeue recipe) lost every metric logged before. :class:`CSVLogger`
keeps the file and its columns. A resumed run repeats the iterations between its checkpoint and the kill;
:class:`ResumeLogs` (a callback) drops their earlier rows from the CSV and tells TensorBoard to discard the
earlier events from that step on (a ``SessionLog.START`` event, what ``SummaryWriter(purge_step=...)`` writes),
so both logs read like those of a run that was never interrupted.
"""

from __future__ import annotations

import csv
import logging
import os
from typing import Any

import lightning as L
from lightning.pytorch.loggers import CSVLogger as _LightningCSVLogger
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment

__all__ = ["CSVLogger", "ResumeLogs"]

log = logging.getLogger(__name__)


class _AppendingWriter(ExperimentWriter):
    """Lightning's CSV writer, minus the deletion of an existing ``metrics.csv`` (its columns are kept)."""

    def _check_log_dir_exists(self) -> None:
        if not os.path.isfile(self.metrics_file_path):
            return
        with open(self.metrics_file_path, newline="") as f:
            header = next(csv.reader(f), [])
        # a later new column rewrites the file with every earlier column too
        self.metrics_keys = sorted(set(header))

    def drop_from(self, step: int) -> int:
        """Remove the rows logged at ``step`` or later (they are about to be logged again); returns how many."""
        self.save()
        if not os.path.isfile(self.metrics_file_path):
            return 0
        with open(self.metrics_file_path, newline="") as f:
            reader = csv.DictReader(f)
            fields = list(reader.fieldnames or [])
            rows = list(reader)
        kept = [r for r in rows if not r.get("step") or int(float(r["step"])) < step]
        if len(kept) < len(rows):
            tmp = f"{self.metrics_file_path}.tmp-{os.getpid()}"
            with open(tmp, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=fields)
                writer.writeheader()
                writer.writerows(kept)
            os.replace(tmp, self.metrics_file_path)
        return len(rows) - len(kept)


class CSVLogger(_LightningCSVLogger):
    """:class:`lightning.pytorch.loggers.CSVLogger` that appends to an existing ``metrics.csv``."""

    @property
    @rank_zero_experiment
    def experiment(self) -> _AppendingWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingWriter(log_dir=self.log_dir)
        return self._experiment


class ResumeLogs(L.Callback):
    """On a resumed run, forget what the logs hold from the resumed iteration on (see the module docstring)."""

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.ckpt_path is None or not trainer.is_global_zero:
            return
        # the step Lightning's loggers use: optimizer steps taken so far
        step = trainer.fit_loop.epoch_loop._batches_that_stepped
        for logger in trainer.loggers:
            if isinstance(logger, CSVLogger):
                dropped = logger.experiment.drop_from(step)
                if dropped:
                    log.info("resumed at step %d: dropped %d later rows of %s", step, dropped, logger.log_dir)
            elif isinstance(logger, TensorBoardLogger):
                _purge_tensorboard(logger, step)


def _purge_tensorboard(logger: TensorBoardLogger, step: int) -> None:
    """Make TensorBoard discard the run's earlier events at ``step`` and later."""
    writer: Any = logger.experiment
    try:
        from tensorboard.compat.proto.event_pb2 import Event, SessionLog
    except ImportError:  # pragma: no cover - tensorboardX's own protos
        from tensorboardX.proto.event_pb2 import Event, SessionLog  # type: ignore[no-redef]
    file_writer = writer._get_file_writer()
    file_writer.add_event(Event(step=step, session_log=SessionLog(status=SessionLog.START)))
    file_writer.flush()
