"""Lightning training of UNICORN: the module, the stage schedule, checkpoints and the DataModule.

- :class:`UnicornLitModule` (``module``): manual optimization alternating pose and 3D steps, one Adam, logging
  of every loss term and of the pose-candidate shares, the non-finite-loss guard.
- :class:`StageCallback`, :class:`ImageLogger` (``callbacks``): progressive conditioning, stage-1 curriculum
  and texture averaging; image logging.
- :class:`AtomicCheckpointIO`, :class:`PeriodicCheckpoint` (``checkpoint``): complete-or-absent, sealed checkpoint
  files read without running code; rotation that counts the files of earlier attempts.
- :class:`CSVLogger`, :class:`TensorBoardLogger`, :class:`ResumeLogs` (``loggers``): logs a resume appends to.
- :class:`HeldOutEvaluation` (``heldout``): held-out metrics every N iterations (learning curves).
- :class:`CodeDiagnostics` (``diagnostics``): code spread and dead units of the code regressors, with a loud
  :class:`CollapseWarning` when a branch stops depending on the image, and the viewpoint health (the pose branch
  on renders at known views, the candidates' shares), with a :class:`ViewpointWarning` when it collapses.
- :func:`~unicorn.lit.run.build`, :func:`~unicorn.lit.run.fit` (``run``): one training run assembled from a
  composed config (run folder, data, module, callbacks and loggers by ``_target_``, trainer), trained and evaluated.
- :class:`GracefulStop` (``signals``): SIGTERM and SIGINT stop training at the next step boundary with
  ``last.ckpt`` written; :class:`ArmStopSignals` puts its handlers in place before any other callback's set-up.
- :class:`UnicornDataModule` (``data``): the one LightningDataModule: a dataset's splits and loaders, training on an
  endless, resumable, rank-sharded stream of batches (:class:`StreamBatchSampler`).

Distributed training (DDP) keeps one neighbour memory bank per rank, as the reference does: each process
searches the neighbours of its own samples among the last ``memory_size`` samples it has seen, with no
communication. Checkpoints gather every rank's bank (and random states) so that a resumed run with the same
number of processes continues exactly; with another number of processes rank ``r`` takes the saved bank of
rank ``r mod saved_world_size``.
"""

from unicorn.lit.callbacks import ImageLogger, ProgressBar, StageCallback, render_overview
from unicorn.lit.checkpoint import AtomicCheckpointIO, PeriodicCheckpoint
from unicorn.lit.data import SeededItems, StreamBatchSampler, UnicornDataModule
from unicorn.lit.diagnostics import (
    CodeDiagnostics,
    CollapseWarning,
    ViewpointWarning,
    code_diagnostics,
    pose_diagnostics,
)
from unicorn.lit.heldout import HeldOutEvaluation
from unicorn.lit.loggers import CSVLogger, ResumeLogs, TensorBoardLogger
from unicorn.lit.module import OPTIM_DEFAULTS, NonFiniteLossError, UnicornLitModule
from unicorn.lit.signals import ArmStopSignals, GracefulStop

__all__ = [
    "OPTIM_DEFAULTS",
    "ArmStopSignals",
    "AtomicCheckpointIO",
    "CodeDiagnostics",
    "CollapseWarning",
    "ViewpointWarning",
    "CSVLogger",
    "GracefulStop",
    "HeldOutEvaluation",
    "ImageLogger",
    "NonFiniteLossError",
    "PeriodicCheckpoint",
    "ProgressBar",
    "ResumeLogs",
    "SeededItems",
    "StageCallback",
    "StreamBatchSampler",
    "TensorBoardLogger",
    "UnicornDataModule",
    "UnicornLitModule",
    "code_diagnostics",
    "pose_diagnostics",
    "render_overview",
]
