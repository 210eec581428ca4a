"""Lightning's side of checkpoints (a CheckpointIO plugin, a rotation callback) on :mod:`unicorn.io.serialization`.

Checkpoints are either complete or absent, sealed with a content hash, and read without running code.

:class:`AtomicCheckpointIO` writes a checkpoint with :func:`unicorn.io.serialization.atomic_save`: to a temporary file
next to its destination, flushed to disk (``fsync``) and renamed into place (``os.replace`` is atomic on POSIX
and Windows), with a SHA-256 of its content stored in it. A run killed while saving (Ctrl-C, SIGKILL, a
pre-empted job) leaves its previous checkpoint intact, at worst with a stray ``.tmp`` file beside it, which the
next run removes (:func:`unicorn.io.serialization.remove_stale_temporaries`). Lightning's own writer renames too
(fsspec transactions) but does not ``fsync``, so a crash of the machine could leave a renamed but incomplete
file. Resuming reads the file with PyTorch's restricted unpickler and checks the hash; a file that needs full
unpickling is refused unless the run trusts it (``trust_checkpoint=true``). Remote paths (``s3://``...) go to
Lightning's reader and writer.
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint

from unicorn.io.checkpoints import check_training_checkpoint
from unicorn.io.run_folder import step_checkpoints
from unicorn.io.serialization import atomic_save, link_into_place, load_checkpoint_file, remove_stale_temporaries

__all__ = ["AtomicCheckpointIO", "PeriodicCheckpoint"]

log = logging.getLogger(__name__)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint I/O with atomic, fsync'ed, sealed local writes and safe reads.

    Pass it in ``Trainer(plugins=[...])``.

    Args:
        trust: read checkpoints with full unpickling (only files from a source you trust: it can run code).
    """

    def __init__(self, trust: bool = False) -> None:
        super().__init__()
        self.trust = trust

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        atomic_save(checkpoint, path)

    def load_checkpoint(self, path: Any, map_location: Any | None = None, weights_only: bool | None = None) -> dict:
        if "://" in str(path):
            return super().load_checkpoint(path, map_location=map_location, weights_only=not self.trust)
        kwargs = {} if map_location is None else {"map_location": map_location}
        data = load_checkpoint_file(path, trust=self.trust, **kwargs)
        check_training_checkpoint(data, path)  # a released model or save_model file: say to use init_from
        return data


class PeriodicCheckpoint(ModelCheckpoint):
    """:class:`~lightning.pytorch.callbacks.ModelCheckpoint` whose rotation also counts files of earlier attempts.

    Lightning only rotates the files it knows from the resumed checkpoint's state; ``step=<N>.ckpt`` files written
    after that checkpoint by a run that was then killed, or by a run started afresh in the folder, would be kept
    forever. At the start of training the folder's ``step=<N>.ckpt`` files are added to the rotation (ranked by
    ``N``, monitor ``"step"``) and the oldest beyond ``save_top_k`` are deleted. Stale ``.tmp`` files of killed
    writes are deleted too.

    The folder's ``last.ckpt`` is the run's own even where this callback did not write it (one an earlier attempt's
    signal wrote): it is replaced, where Lightning would write ``last-v1.ckpt`` beside it. At a periodic save it is
    a second name (a hard link) of that iteration's ``step=<N>.ckpt``: one write, and no moment at which the two
    files hold different iterations. With ``save_last``, training ends with ``last.ckpt`` of the final iteration,
    written once: at the end of training unless a periodic save (or a signal's, :meth:`save_last_checkpoint`) just
    wrote it; without it, a training that reaches ``max_steps`` between two periodic saves ends with one more
    ``step=<N>.ckpt`` of its final iteration (unless ``save_top_k`` is 0).
    """

    def _save_last_checkpoint(self, trainer: L.Trainer, monitor_candidates: dict[str, torch.Tensor]) -> None:
        source = self._last_checkpoint_saved  # the periodic file of this iteration, if one was just written
        periodic = self.save_last is True and source and self._last_global_step_saved == trainer.global_step
        if not periodic or "://" in str(source):  # nothing to link to (or a remote store): written in full
            super()._save_last_checkpoint(trainer, monitor_candidates)
            return
        # last.ckpt is a second name of the periodic file: written in microseconds, so that no kill falls between
        # the two (a resume would go back to the save before, and delete this one with the iterations it holds)
        last = self.format_checkpoint_name(monitor_candidates, self.CHECKPOINT_NAME_LAST)
        previous, self.last_model_path = self.last_model_path, last
        if trainer.is_global_zero:
            link_into_place(source, last)
        trainer.strategy.barrier()
        if previous and previous != last and self._should_remove_checkpoint(trainer, previous, last):
            self._remove_checkpoint(trainer, previous)

    @property
    def last_file(self) -> Path | None:
        """The ``last.ckpt`` this callback writes (None without ``save_last``)."""
        if not self.save_last or self.dirpath is None:
            return None
        return Path(self.format_checkpoint_name({}, self.CHECKPOINT_NAME_LAST))

    def save_last_checkpoint(self, trainer: L.Trainer) -> None:
        """Write :attr:`last_file` of the current iteration, unless this callback already wrote it (a periodic save
        of the same iteration). The same decision on every rank."""
        if self.save_last and self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    def note_saved(self, trainer: L.Trainer) -> None:
        """The current iteration was saved by another writer (a signal's ``last.ckpt``): the end of training does
        not save it again."""
        self._last_global_step_saved = trainer.global_step

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        with warnings.catch_warnings():
            # a folder holding checkpoints is one the run may use (a resume, overwrite=true): the run folder's
            # checks decide that before training (unicorn.io.run_folder), Lightning's note would only alarm
            warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
            super().setup(trainer, pl_module, stage)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Lightning's own end-of-training save is made only where nothing was saved during the run
        if self.save_last:
            self.save_last_checkpoint(trainer)
        elif self._last_global_step_saved != trainer.global_step and 0 < trainer.max_steps <= trainer.global_step:
            # without last.ckpt the final iterations would be lost: the end is one more step=<N>.ckpt (rotated)
            self._save_topk_checkpoint(trainer, self._monitor_candidates(trainer))

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_start(trainer, pl_module)
        if self.dirpath is None:
            return
        if self.save_last:
            last = self.format_checkpoint_name({}, self.CHECKPOINT_NAME_LAST)
            if self.file_exists(last, trainer):  # on every rank: rank 0 looks, the others are told
                self.last_model_path = last
        if not trainer.is_global_zero or not os.path.isdir(self.dirpath):
            return
        remove_stale_temporaries(self.dirpath)
        if self.monitor != "step" or self.save_top_k < 0:
            return
        for step, path in step_checkpoints(Path(self.dirpath)):
            if step > trainer.global_step:
                # written after the checkpoint this run resumes from by an attempt that was then killed: it is
                # about to be written again (Lightning would otherwise write a "-v1" copy beside it)
                self.best_k_models.pop(str(path), None)
                log.info("removing %s, newer than the resumed iteration %d", path, trainer.global_step)
                trainer.strategy.remove_checkpoint(path)
            elif str(path) not in self.best_k_models:
                self.best_k_models[str(path)] = torch.tensor(float(step))
        ranked = sorted(self.best_k_models, key=lambda p: float(self.best_k_models[p]))
        for stale in ranked[: max(0, len(ranked) - self.save_top_k)]:
            self.best_k_models.pop(stale)
            if os.path.isfile(stale):
                log.info("removing %s (beyond the %d kept checkpoints)", stale, self.save_top_k)
                trainer.strategy.remove_checkpoint(stale)
        if self.best_k_models:
            self.best_model_path = max(self.best_k_models, key=lambda p: float(self.best_k_models[p]))
            self.best_model_score = self.best_k_models[self.best_model_path]
            if len(self.best_k_models) == self.save_top_k:
                self.kth_best_model_path = min(self.best_k_models, key=lambda p: float(self.best_k_models[p]))
                self.kth_value = self.best_k_models[self.kth_best_model_path]
