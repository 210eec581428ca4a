"""Metric logs that survive a resume: the CSV is appended to, not rewritten, and neither log repeats iterations.

Lightning's :class:`~lightning.pytorch.loggers.CSVLogger` deletes ``metrics.csv`` when its folder exists, so
resuming a run in its own folder (the SLURM requeue recipe) would lose every metric logged. :class:`CSVLogger`
keeps the file and its columns, and rewrites it (a new column, a resume) by replacing it whole. A resumed run
repeats the iterations between its checkpoint and the kill; :class:`ResumeLogs` (a callback) drops their earlier
rows from the CSV and tells TensorBoard to discard the earlier events from that step on (a ``SessionLog.START``
event, what ``SummaryWriter(purge_step=...)`` writes), so both logs read like those of a run that was never
interrupted.

Both logs use Lightning's logging step: iteration N's training values are logged at step N - 1, and so are the
evaluations made at the end of iteration N (:func:`log_step`), so that a checkpoint after iteration N splits the
logs at step N exactly.
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
from collections.abc import Callable, Mapping
from typing import Any

import lightning as L
from lightning.pytorch.loggers import CSVLogger as _LightningCSVLogger
from lightning.pytorch.loggers import TensorBoardLogger as _LightningTensorBoardLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment
from lightning.pytorch.utilities import rank_zero_only

__all__ = ["CSVLogger", "ResumeLogs", "TensorBoardLogger", "log_step", "logs_this_step"]

log = logging.getLogger(__name__)


def logs_this_step(trainer: L.Trainer | None) -> bool:
    """Whether the loggers write the coming (or current) iteration's step values (``trainer.log_every_n_steps``).

    Lightning drops the step values of other iterations; skipping their ``log`` calls saves their cost (a few
    percent of a CPU training step). True without a trainer.
    """
    connector = getattr(trainer, "_logger_connector", None)  # Lightning's own test, where it exists
    return bool(getattr(connector, "should_update_logs", True))


def log_step(iteration: int) -> int:
    """The loggers' step of values computed at the end of iteration ``iteration`` (a held-out evaluation, code
    diagnostics): ``iteration - 1``, where Lightning logs that iteration's training values; 0 before training."""
    return max(int(iteration) - 1, 0)


class _AppendingWriter(ExperimentWriter):
    """Lightning's CSV writer, minus the deletion of an existing ``metrics.csv`` (its columns are kept, in their
    order: rows are appended under the file's own header)."""

    def _check_log_dir_exists(self) -> None:
        if not os.path.isfile(self.metrics_file_path):
            return
        with open(self.metrics_file_path, newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), [])
        # the file's order, which need not be sorted (a file of another writer): appended rows follow it
        self.metrics_keys = list(dict.fromkeys(header))

    def _record_new_keys(self) -> set[str]:
        """Add the columns of the pending rows that the file lacks; the columns are sorted only when some are new
        (the file is then written anew under the new header), so that rows appended to an existing file follow its
        header whatever its order."""
        new_keys = set().union(*self.metrics) - set(self.metrics_keys)
        if new_keys:
            self.metrics_keys = sorted({*self.metrics_keys, *new_keys})
        return new_keys

    def save(self) -> None:
        """Append the rows logged since the last save (the header first in a new file; the whole file rewritten when
        they bring a new column), in UTF-8 as the file is read, whatever the locale."""
        if not self.metrics:
            return
        new_keys = self._record_new_keys()
        exists = os.path.isfile(self.metrics_file_path)
        if new_keys and exists:
            self._rewrite_with_new_header(self.metrics_keys)
        with open(self.metrics_file_path, "a" if exists else "w", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=self.metrics_keys)
            if not exists:
                writer.writeheader()
            writer.writerows(self.metrics)
        self.metrics = []

    def drop_from(self, step: int) -> int:
        """Remove the rows logged at ``step`` or later (they are about to be logged again), and a last row cut
        short (a run killed while writing it: the rows appended next would continue its line); returns how many
        rows were logged at ``step`` or later."""
        self.save()
        if not os.path.isfile(self.metrics_file_path):
            return 0
        fields, rows, damaged = self._read()
        kept = [r for r in rows if not r.get("step") or int(float(r["step"])) < step]
        if damaged:
            log.warning("%s: dropped %d row(s) cut short or of the wrong width", self.metrics_file_path, damaged)
        if len(kept) < len(rows) or damaged:
            self._replace(fields, kept)
        return len(rows) - len(kept)

    def _rewrite_with_new_header(self, fieldnames: list[str]) -> None:
        # Lightning's rewrites the file in place: a kill or a full disk part-way would lose every row
        self._replace(fieldnames, self._read()[1])

    def _read(self) -> tuple[list[str], list[dict[str, str]], int]:
        """The columns, the rows as tables, and how many rows were left out as damaged: a last row without its
        line end, or a row of another width than the header."""
        with open(self.metrics_file_path, newline="", encoding="utf-8") as f:
            text = f.read()
        header, *lines = list(csv.reader(io.StringIO(text))) or [[]]
        whole = lines if text.endswith(("\n", "\r")) else lines[:-1]
        rows = [dict(zip(header, line, strict=True)) for line in whole if len(line) == len(header)]
        return header, rows, len(lines) - len(rows)

    def _replace(self, fields: list[str], rows: list[dict[str, str]]) -> None:
        """Write ``metrics.csv`` anew beside it, then rename it into place (whole or not at all)."""
        from unicorn.io.serialization import replacing

        with replacing(self.metrics_file_path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            writer.writerows(rows)


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
    """:class:`lightning.pytorch.loggers.TensorBoardLogger` that writes events as they are logged, and whose
    failures do not end the run.

    TensorBoard reads every event file of the folder, so a resumed run's earlier events stay; :class:`ResumeLogs`
    hides those it is about to repeat. Events that cannot be written (the folder deleted while the run goes on, a
    full disk) are tried once more in a new event file; if that fails too, TensorBoard logging stops with a
    warning and training goes on (the CSV log and the checkpoints are written as before).
    """

    #: the error that stopped this logger's events (None: logging)
    failure: OSError | None = None

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        def write() -> None:
            super(TensorBoardLogger, self).log_metrics(metrics, step)
            # written as logged (SummaryWriter buffers up to two minutes, which a killed run lost, including
            # iterations its last checkpoint already holds); logging happens every log_every_n_steps iterations
            self.experiment.flush()

        self.write_events(write)

    def log_image(self, tag: str, image: Any, step: int) -> None:
        """Add ``image`` (C, H, W) in [0, 1] under ``tag`` at ``step``, written at once."""

        def write() -> None:
            self.experiment.add_image(tag, image, step)
            self.experiment.flush()

        self.write_events(write)

    def write_events(self, write: Callable[[], None]) -> None:
        """Run ``write`` (calls of :attr:`experiment`); on an I/O error run it once more with a new writer (and
        event file), then give TensorBoard logging up (:attr:`failure`) with a warning."""
        if self.failure is not None:
            return
        if self._experiment is not None and not os.path.isdir(self.log_dir):  # deleted while the run goes on
            self._drop_writer()  # before its thread fails to append to the file that was there
        for attempt in range(2):
            try:
                write()
                return
            except (OSError, ValueError) as err:  # Lightning's log_metrics reraises any error as a ValueError
                cause = err if isinstance(err, OSError) else err.__cause__
                if not isinstance(cause, OSError):
                    raise
                self._drop_writer()
                if attempt:
                    self.failure = cause
                    log.warning(
                        "TensorBoard events cannot be written to %s (%s): TensorBoard logging stops here, training "
                        "goes on",
                        self.log_dir,
                        cause,
                    )

    def _drop_writer(self) -> None:
        """Forget the SummaryWriter (its thread may hold the error), so that the next use opens a new one."""
        writer, self._experiment = self._experiment, None
        if writer is not None:
            with contextlib.suppress(Exception):
                writer.close()

    @rank_zero_only
    def finalize(self, status: str) -> None:
        if self.failure is None:
            self.write_events(lambda: super(TensorBoardLogger, self).finalize(status))


class ResumeLogs(L.Callback):
    """On a resumed run, forget what the logs hold from the resumed iteration on (see the module docstring): the
    CSV rows at the checkpoint's step (iteration N's checkpoint: step N, where iteration N + 1 logs) and later
    are dropped, and TensorBoard is told to discard its events from that step on.

    Args:
        resume: the run resumes (or restarts) in its own folder; when False nothing is done.
    """

    def __init__(self, resume: bool = True) -> None:
        self.resume = resume

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.resume or not trainer.is_global_zero:
            return
        step = int(trainer.global_step)  # the iterations done, the logging step of the next one
        for logger in trainer.loggers:
            if isinstance(logger, CSVLogger):
                dropped = logger.experiment.drop_from(step)
                if dropped:
                    log.info("resumed at iteration %d: dropped %d later rows of %s", step, dropped, logger.log_dir)
            elif isinstance(logger, TensorBoardLogger):
                _purge_tensorboard(logger, step)


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
