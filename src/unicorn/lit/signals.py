"""Stopping a run cleanly on SIGTERM or SIGINT: at the next step boundary, with ``last.ckpt`` written.

Schedulers (SLURM, Kubernetes...) send SIGTERM before they preempt or requeue a job; Ctrl-C sends SIGINT.
:class:`GracefulStop` lets the iteration under way finish, writes ``last.ckpt`` atomically
(:class:`~unicorn.lit.checkpoint.AtomicCheckpointIO`), whatever ``callbacks.checkpoint.save_last`` says, at the
point of the iteration where the periodic checkpoints are written (after them: it is a Lightning ``Checkpoint``
callback, and those run last, in their order), and stops before the next iteration (once
the loggers have the iteration's values, as a resume expects them) with :class:`unicorn.errors.Interrupted`:
``unicorn-train`` then exits with status ``128 + signal`` (143 for SIGTERM, 130 for SIGINT), never 0. The same
command with ``ckpt_path=last`` (a requeued SLURM job) resumes from that file exactly.

During training the callback handles SIGTERM and SIGINT itself, in place of Lightning's SIGTERM handler (which
raises as soon as it sees its flag, with no checkpoint written when the signal arrives after this callback's
check); a SIGTERM that Lightning's handler still records (``trainer.received_sigterm``) is honoured the same way,
and a second signal stops at once (no checkpoint written; the same exit status). Under DDP every rank stops at the same
iteration: the decision is reduced across ranks at each step boundary. The handlers are in place from the first
``on_train_start`` hook on (:class:`ArmStopSignals`, first among the callbacks; Lightning runs checkpoint callbacks
after all others). Before that, from the start of ``Trainer.fit``, Lightning's handler only records the signal
(:func:`record_only_sigterm`) and the command's own (:func:`unicorn.errors.interrupt_on_signal`) stops at once: as
Lightning ships it, the handler broadcasts to the other DDP ranks from inside the handler, and a rank that gets the
signal while another waits in a different collective (rank 0 setting up its held-out scoring while the others wait
at a callback's barrier) never returns.

Outside the training iterations (building the run, the evaluation after training) there is no step boundary to
wait for: inside :func:`unicorn.errors.interrupt_on_signal` SIGTERM and SIGINT raise
:class:`~unicorn.errors.Interrupted` at once, so that the command cleans up (its lock, a folder left as it was before
the first iteration), says where it stopped and exits with ``128 + signal``; a second signal stops at once.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Checkpoint

from unicorn.errors import Interrupted, handle_stop_signals, pending_interrupt, restore_handlers
from unicorn.io.run_folder import resume_hint
from unicorn.lit.checkpoint import PeriodicCheckpoint

__all__ = ["ArmStopSignals", "GracefulStop", "record_only_sigterm"]

log = logging.getLogger("unicorn.train")


class GracefulStop(Checkpoint):
    """Stop at the step boundary after SIGTERM or SIGINT, writing ``last_path`` first (see the module docstring).

    Where a :class:`~unicorn.lit.checkpoint.PeriodicCheckpoint` before it in the trainer's callbacks keeps
    ``last_path`` as its ``last.ckpt``, that callback writes it (once per iteration: not again after its periodic
    save of the same iteration, nor at the end of training).

    Its :class:`ArmStopSignals` counts the iterations this process ran (:attr:`steps_run`): a run that fails before
    its first one leaves its folder as it found it (:mod:`unicorn.cli.train`).

    Args:
        last_path: where the checkpoint of an interrupted run goes (the run's ``checkpoints/last.ckpt``).
    """

    def __init__(self, last_path: str | Path) -> None:
        self.last_path = Path(last_path)
        self.steps_run = 0
        self.received: int | None = None
        #: the second signal, which stopped the run at once (no checkpoint written), or None
        self.at_once: int | None = None
        #: the error ending an interrupted run, once its checkpoint is written (raised by :func:`unicorn.lit.run.fit`
        #: or before the next iteration)
        self.stopped: Interrupted | None = None
        self._previous: dict[int, Any] = {}
        self._armed = False

    def arm(self) -> None:
        """Handle SIGTERM and SIGINT from now on until the end of this fit (once per fit; the first
        ``on_train_start`` hook calls it: :class:`ArmStopSignals`).

        Raises:
            unicorn.errors.Interrupted: a signal arrived while the run was built (its error swallowed there).
        """
        if self._armed:
            return
        self._armed = True
        self.received, self.stopped, self.at_once = None, None, None
        late = pending_interrupt("before the first iteration")  # its error swallowed while the run was built
        if late is not None:
            raise late
        if threading.current_thread() is threading.main_thread():
            # SIGTERM too, in place of Lightning's handler (see the module docstring)
            self._previous = handle_stop_signals(self._on_signal)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.arm()

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self.received is not None:  # asked twice: stop now
            self._restore()
            self.at_once = signum  # Lightning ends a KeyboardInterrupt with sys.exit(1): unicorn.lit.run.fit says why
            raise KeyboardInterrupt
        self.received = signum
        log.warning("%s: stopping after this iteration (again to stop at once)", signal.Signals(signum).name)

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        signum = self.received or (signal.SIGTERM if trainer.received_sigterm else None)
        if not trainer.strategy.reduce_boolean_decision(signum is not None, all=False):
            return
        signum = signum or signal.SIGTERM
        self._save(trainer)
        self.stopped = Interrupted(
            f"stopped by {signal.Signals(signum).name} after iteration {trainer.global_step}; {self.last_path} "
            f"written: the same command with {resume_hint(self.last_path.parent.parent)} resumes it",
            128 + signum,
        )

    def _save(self, trainer: L.Trainer) -> None:
        own = Path(os.path.realpath(self.last_path))  # as ModelCheckpoint resolves its dirpath
        for callback in trainer.checkpoint_callbacks:
            if isinstance(callback, PeriodicCheckpoint) and callback.last_file == own:
                callback.save_last_checkpoint(trainer)
                return
        trainer.save_checkpoint(self.last_path, weights_only=False)
        for callback in trainer.checkpoint_callbacks:
            if isinstance(callback, PeriodicCheckpoint):
                callback.note_saved(trainer)

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        # the iteration that saw the signal has been logged like any other: stop before the next one runs
        if self.stopped is not None:
            raise self.stopped

    def _restore(self) -> None:
        restore_handlers(self._previous)
        self._previous = {}
        self._armed = False

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._restore()


class ArmStopSignals(L.Callback):
    """Puts ``stopper``'s signal handlers in place at the first ``on_train_start`` hook (:meth:`GracefulStop.arm`):
    first in the trainer's callbacks, before any other callback's set-up (see the module docstring); and counts the
    iterations run (``stopper.steps_run``) before any other callback's end-of-iteration hook."""

    def __init__(self, stopper: GracefulStop) -> None:
        self.stopper = stopper

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.stopper.arm()

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        # counted here, first of the callbacks: an iteration that ran counts even when a later callback fails
        self.stopper.steps_run += 1


def record_only_sigterm(trainer: L.Trainer) -> None:
    """Make ``trainer``'s own SIGTERM handler only record the signal (``trainer.received_sigterm``), without
    forwarding it to the processes it launched or broadcasting from inside the handler (see the module docstring).

    Lightning's signal connector reads its handler from the attribute ``_sigterm_notifier_fn`` when ``fit`` installs
    it; a Lightning without that attribute is left as it is.
    """
    connector = getattr(trainer, "_signal_connector", None)
    if connector is None or not hasattr(connector, "_sigterm_notifier_fn"):
        return

    def record(signum: int, frame: Any) -> None:
        connector.received_sigterm = True

    connector._sigterm_notifier_fn = record
