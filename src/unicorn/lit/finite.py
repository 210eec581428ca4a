"""The trainer's finite-loss check: stop on a NaN or infinite loss or gradient, keeping the last good state.

Under a loss scaler (``trainer.precision=16-mixed``) only the loss terms are checked: the scaled gradients overflow
now and then by design, and the scaler skips those steps.

Two ways, the same verdict on the iteration that went wrong:

- :meth:`FiniteCheck.now` (the default, and the CPU's): every step reduces the terms and the gradients to one flag
  on the device and reads it before the optimizer steps, so a non-finite update is never applied; the forward
  pass's other changes (BatchNorm statistics, neighbour memory) are undone and the state before the iteration is
  saved to ``nonfinite-step=<N>.ckpt``;
- :meth:`FiniteCheck.defer` then :meth:`FiniteCheck.verify` (the trainer's steps without host reads, on CUDA): each
  step folds its flag into one on the device and notes the first bad iteration there; the logging steps read it.
  Each good verification keeps a copy on the device of the module's state, the optimizers' and schedulers' states
  and the neighbour memory, the state to roll back to; a bad one restores it and saves it (as
  ``nonfinite-step=<N>.ckpt``, N the verified iteration) before stopping.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils._pytree import TreeSpec, tree_flatten, tree_unflatten

from unicorn.errors import UserError

__all__ = ["FiniteCheck", "NonFiniteLossError"]

log = logging.getLogger(__name__)


class NonFiniteLossError(UserError, FloatingPointError):
    """A loss term or a gradient became NaN or infinite; the message names the iteration and the term."""


def _finite(losses: Mapping[str, torch.Tensor], grads: list[torch.Tensor]) -> torch.Tensor:
    """0-dim bool on the device: every term (each 0-dim) and the gradients' total norm finite."""
    finite = torch.isfinite(torch.stack([v.detach() for v in losses.values()])).all()
    if grads:
        finite = finite & torch.isfinite(torch.nn.utils.get_total_norm(grads))
    return finite


def _same_tensor_layout(kept: Any, live: Any) -> bool:
    """Whether ``live`` can be copied into ``kept``: both tensors of one shape, type and device, or neither a tensor."""
    if not isinstance(live, torch.Tensor):
        return not isinstance(kept, torch.Tensor)
    return (
        isinstance(kept, torch.Tensor)
        and kept.shape == live.shape
        and kept.dtype == live.dtype
        and kept.device == live.device
    )


def _listed(items: Any) -> list[Any]:
    """Lightning's one-or-several (or None) as a list."""
    return [] if items is None else items if isinstance(items, list) else [items]


class FiniteCheck:
    """The finite-loss check of one :class:`~unicorn.lit.UnicornLitModule` (see the module docstring)."""

    def __init__(self, module: L.LightningModule) -> None:
        self.module = module
        # the forward pass's changes besides the parameters, kept to be undone (see snapshot)
        self._buffers: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None
        # the deferred check: its flag, first bad iteration and phase (on the device) and the state to roll back to
        self._bad: torch.Tensor | None = None
        self._good: tuple[int, dict[str, Any]] | None = None
        self._kept: tuple[TreeSpec, list[Any]] | None = None  # the copies of the last _state (its layout, leaves)
        self._params: list[torch.nn.Parameter] | None = None  # the model's parameters (_grads)

    # ------------------------------------------------------------------ every step
    def snapshot(self) -> None:
        """Keep what the forward pass changes besides the parameters: the BatchNorm running statistics (copied
        into buffers kept for it, one fused copy per step) and the neighbour memory (whose next push keeps the rows
        it overwrites). :meth:`restore_forward` puts them back."""
        if self._buffers is None:
            model = self.module.model
            norms = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
            live = [b for m in norms for b in (m.running_mean, m.running_var, m.num_batches_tracked) if b is not None]
            self._buffers = (live, [b.clone() for b in live])
        live, saved = self._buffers
        if live:
            torch._foreach_copy_(saved, live)
        self.module.objectives.memory.forget_push()

    def restore_forward(self) -> None:
        live, saved = self._buffers or ([], [])
        if live:
            torch._foreach_copy_(live, saved)
        self.module.objectives.memory.undo_push()

    def _grads(self) -> list[torch.Tensor]:
        """The gradients to check; none under a loss scaler (``trainer.precision=16-mixed``): its gradients are
        scaled, and an overflow is the scaler's to handle (it skips that step and lowers the scale)."""
        if getattr(self.module.trainer.precision_plugin, "scaler", None) is not None:
            return []
        if self._params is None:  # listed once: walking the modules at every step costs Python time
            self._params = list(self.module.model.parameters())
        return [p.grad for p in self._params if p.grad is not None]

    def now(self, losses: Mapping[str, torch.Tensor], step: int, phase: str) -> None:
        """Raise :class:`NonFiniteLossError` (after saving a checkpoint) if a term or a gradient is not finite.

        The parameters are still those before this iteration and the forward pass's other changes are undone
        before saving, so the checkpoint is the state after the last good iteration. The decision is reduced over
        ranks so that every process stops (and saves) together.
        """
        # everything reduced to one flag on the device and read once: the single host sync of a step, needed
        # because the optimizer must not apply a non-finite update
        grads = self._grads()
        flag = (~_finite(losses, grads)).float()
        trainer = self.module.trainer
        if trainer.world_size > 1:
            flag = trainer.strategy.reduce(flag, reduce_op="max")
        if float(flag) == 0:
            return
        bad = [f"{k} = {float(v.detach()):g}" for k, v in losses.items() if not torch.isfinite(v).all()]
        if not bad and grads and not torch.isfinite(torch.nn.utils.get_total_norm(grads)):
            bad.append("gradients of 'total' (finite loss)")
        self.stop(step, phase, ", ".join(bad) if bad else "a term on another rank")

    def stop(self, step: int, phase: str, where: str) -> None:
        """Undo the forward pass of iteration ``step`` (begun after :meth:`snapshot`), save the state before it and
        raise :class:`NonFiniteLossError` naming ``where`` (the terms, or the values, that were not finite).

        Raises:
            NonFiniteLossError: always.
        """
        self.restore_forward()
        path = self._save(step)
        saved = f"; the state before this iteration was saved to {path}" if path else ""
        raise NonFiniteLossError(f"non-finite loss at iteration {step} ({phase} step): {where}{saved}")

    # ------------------------------------------------------------------ deferred to the logging steps
    def begin(self, step: int) -> None:
        """Before the forward pass of iteration ``step``: keep the state to roll back to if there is none yet."""
        if self._good is None:
            self._good = (step, self._state())

    def defer(self, losses: Mapping[str, torch.Tensor], step: int) -> None:
        """Fold iteration ``step``'s flag into the device's record (no host read): the first bad iteration, and
        which of its terms were not finite."""
        values = torch.stack([v.detach() for v in losses.values()])
        bad = ~_finite(losses, self._grads())
        if self._bad is None:
            self._bad = torch.full((), -1, dtype=torch.long, device=values.device)
            # per step kind and set of terms (a stage can add one): which terms the first bad iteration had
            self._terms: dict[tuple[str, tuple[str, ...]], torch.Tensor] = {}
        first = bad & (self._bad < 0)
        self._bad = torch.where(first, step, self._bad)
        key = (self.module.phase(step), tuple(losses))
        flags = first & ~torch.isfinite(values)  # set once, by the first bad iteration
        before = self._terms.get(key)
        self._terms[key] = flags if before is None else before | flags

    def verify(self, step: int) -> None:
        """After iteration ``step``: read the record (one host read); keep the state as the one to roll back to,
        or restore and save the kept one and raise :class:`NonFiniteLossError`."""
        if self._bad is None:
            return
        first = self._bad
        trainer = self.module.trainer
        if trainer.world_size > 1:
            first = trainer.strategy.reduce(first.float(), reduce_op="max").long()
        first = int(first)
        if first < 0:
            self._good = (step + 1, self._state())
            return
        phase, bad = self.module.phase(first), []
        for (kind, names), flags in self._terms.items():
            if kind == phase:
                bad += [name for name, flag in zip(names, flags.tolist()) if flag]
        bad = bad or ["gradients of 'total' or another rank"]
        good_step, state = self._good or (0, None)
        path = self._roll_back(good_step, state) if state is not None else None
        saved = f"; the state after iteration {good_step - 1} was saved to {path}" if path else ""
        raise NonFiniteLossError(
            f"non-finite loss at iteration {first} ({self.module.phase(first)} step), found at iteration {step}: "
            f"{', '.join(bad)}{saved}"
        )

    def _state(self) -> dict[str, Any]:
        """The state to roll back to, copied on the device: the module's weights and buffers, the optimizers'
        and schedulers' states and the neighbour memory.

        The copies are kept from one call to the next: where the live state has the same layout as at the last
        call (the same keys, and tensors of the same shapes, types and devices), its tensors are copied into them
        in one fused copy per device rather than into new tensors one by one; a new layout (a stage's first
        optimizer states, the neighbour memory's first push) is copied anew.
        """
        module = self.module
        live = {
            "module": module.state_dict(),
            "optimizers": [o.optimizer.state_dict() for o in _listed(module.optimizers())],
            "schedulers": [s.state_dict() for s in _listed(module.lr_schedulers())],
            "memory": module.objectives.memory.state(copy=False),
        }
        leaves, spec = tree_flatten(live)
        kept = self._kept[1] if self._kept is not None and self._kept[0] == spec else None
        if kept is not None and all(map(_same_tensor_layout, kept, leaves)):
            by_device: dict[torch.device, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
            for k, v in zip(kept, leaves):
                if isinstance(v, torch.Tensor):  # one fused copy per device (an optimizer's steps may be on the host)
                    targets, sources = by_device.setdefault(v.device, ([], []))
                    targets.append(k)
                    sources.append(v.detach())
            for targets, sources in by_device.values():
                torch._foreach_copy_(targets, sources)
            copies = [k if isinstance(v, torch.Tensor) else copy.deepcopy(v) for k, v in zip(kept, leaves)]
        else:
            copies = [v.detach().clone() if isinstance(v, torch.Tensor) else copy.deepcopy(v) for v in leaves]
        self._kept = (spec, copies)
        return tree_unflatten(copies, spec)

    def _roll_back(self, step: int, state: dict[str, Any]) -> str | None:
        """Put ``state`` (kept before iteration ``step``) back and save it as the checkpoint of iteration ``step``."""
        module = self.module
        module.load_state_dict(state["module"])
        for opt, saved in zip(_listed(module.optimizers()), state["optimizers"]):
            opt.optimizer.load_state_dict(saved)
        for sched, saved in zip(_listed(module.lr_schedulers()), state["schedulers"]):
            sched.load_state_dict(saved)
        module.objectives.memory.load_state(state["memory"])
        progress = module.trainer.fit_loop.epoch_loop.manual_optimization.optim_step_progress.total
        progress.completed = progress.ready = step  # the checkpoint's global_step: the iteration it resumes at
        return self._save(step)

    def _save(self, step: int) -> str | None:
        trainer = self.module.trainer
        callback = trainer.checkpoint_callback
        folder = getattr(callback, "dirpath", None) or Path(trainer.default_root_dir) / "checkpoints"
        path = Path(folder) / f"nonfinite-step={step}.ckpt"
        try:
            trainer.save_checkpoint(path)
        except Exception as err:  # saving is best effort: the error message matters more
            log.error("could not save a checkpoint before stopping: %s", err)
            return None
        return str(path)
