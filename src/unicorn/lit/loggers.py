"""Metric logs that survive a resume: the CSV is appended to, not rewritten, and neither log repeats iterations.

Lightning's :class:`~lightning.pytorch.loggers.CSVLogger` deletes ``metrics.csv`` when its folder exists, so
resuming a run in its own folder (the SLURM requeue recipe) would lose every metric logged. :class:`CSVLogger`
keeps the file and its columns. A resumed run repeats the iterations between its checkpoint and the kill;
:class:`ResumeLogs` (a callback) drops their earlier rows from the CSV and tells TensorBoard to discard the
earlier events from that step on (a ``SessionLog.START`` event, what ``SummaryWriter(purge_step=...)`` writes),
so both logs read like those of a run that was never interrupted.
"""

from __future__ import annotations

import csv
import logging
import os
from collections.abc import Mapping
from typing import Any

import lightning as L
from lightning.pytorch.loggers import CSVLogger as _LightningCSVLogger
from lightning.pytorch.loggers import TensorBoardLogger as _LightningTensorBoardLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment

__all__ = ["CSVLogger", "ResumeLogs", "TensorBoardLogger", "logs_this_step"]

log = logging.getLogger(__name__)


def logs_this_step(trainer: L.Trainer | None) -> bool:
    """Whether the loggers write the coming (or current) iteration's step values (``trainer.log_every_n_steps``).

    Lightning drops the step values of other iterations; skipping their ``log`` calls saves their cost (a few
    percent of a CPU training step). True without a trainer.
    """
    connector = getattr(trainer, "_logger_connector", None)  # Lightning's own test, where it exists
    return bool(getattr(connector, "should_update_logs", True))


class _AppendingWriter(ExperimentWriter):
    """Lightning's CSV writer, minus the deletion of an existing ``metrics.csv`` (its columns are kept)."""

    def _check_log_dir_exists(self) -> None:
        if not os.path.isfile(self.metrics_file_path):
            return
        with open(self.metrics_file_path, newline="") as f:
            header = next(csv.reader(f), [])
        # a later new column rewrites the file with every earlier column too
        self.metrics_keys = sorted(set(header))

    #: set on resume: the first row logged drops the earlier rows from its step on
    resume_pending = False

    def log_metrics(self, metrics_dict: dict[str, float], step: int | None = None) -> None:
        if self.resume_pending and step is not None:
            self.resume_pending = False
            dropped = self.drop_from(step)
            if dropped:
                log.info("resumed at logged step %d: replaced %d later rows of %s", step, dropped, self.log_dir)
        super().log_metrics(metrics_dict, step)

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
    """:class:`lightning.pytorch.loggers.CSVLogger` that appends to an existing ``metrics.csv``.

    Rows are written as they are logged (``flush_logs_every_n_steps=1``: Lightning buffers 100, which a killed
    run lost, including rows of iterations its checkpoint already holds) and again with every checkpoint.
    """

    def __init__(self, *args: Any, flush_logs_every_n_steps: int = 1, **kwargs: Any) -> None:
        super().__init__(*args, flush_logs_every_n_steps=flush_logs_every_n_steps, **kwargs)

    def after_save_checkpoint(self, checkpoint_callback: Any) -> None:
        super().after_save_checkpoint(checkpoint_callback)
        self.save()

    @property
    @rank_zero_experiment
    def experiment(self) -> _AppendingWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingWriter(log_dir=self.log_dir)
        return self._experiment


class TensorBoardLogger(_LightningTensorBoardLogger):
    """:class:`lightning.pytorch.loggers.TensorBoardLogger` that writes events as they are logged and, on resume,
    hides the events it is about to repeat.

    TensorBoard reads every event file of the folder, so the earlier run's events stay; the first metrics logged
    after a resume are preceded by a ``SessionLog.START`` event at their step, after which TensorBoard discards
    the earlier events at that step and later (what ``SummaryWriter(purge_step=...)`` writes).
    """

    #: set on resume (by :class:`ResumeLogs`)
    resume_pending = False

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        if self.resume_pending and step is not None:
            self.resume_pending = False
            _purge_tensorboard(self, step)
        super().log_metrics(metrics, step)
        # written as logged (SummaryWriter buffers up to two minutes, which a killed run lost, including
        # iterations its last checkpoint already holds); logging happens every log_every_n_steps iterations
        self.experiment.flush()


class ResumeLogs(L.Callback):
    """On a resumed run, forget what the logs hold from the resumed iteration on (see the module docstring).

    The step is that of the first metrics the resumed run logs (Lightning's logging step is not the checkpoint's
    ``global_step``), so the loggers act when they get them.

    Args:
        resume: the run resumes (or restarts) in its own folder; when False nothing is done.
    """

    def __init__(self, resume: bool = True) -> None:
        self.resume = resume

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.resume or not trainer.is_global_zero:
            return
        for logger in trainer.loggers:
            if isinstance(logger, CSVLogger):
                logger.experiment.resume_pending = True
            elif isinstance(logger, TensorBoardLogger):
                logger.resume_pending = True


def _purge_tensorboard(logger: _LightningTensorBoardLogger, step: int) -> None:
    """Make TensorBoard discard the run's earlier events at ``step`` and later."""
    writer: Any = logger.experiment
    try:
        from tensorboard.compat.proto.event_pb2 import Event, SessionLog
    except ImportError:  # pragma: no cover - tensorboardX's own protos
        from tensorboardX.proto.event_pb2 import Event, SessionLog  # type: ignore[no-redef]
    file_writer = writer._get_file_writer()
    file_writer.add_event(Event(step=step, session_log=SessionLog(status=SessionLog.START)))
    file_writer.flush()
