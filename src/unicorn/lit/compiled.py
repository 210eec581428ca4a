"""A training step's forward compiled whole: the networks, the renderer and the losses as one graph.

``model.compile_scope=step`` compiles what the trainer's steps without host reads (:mod:`unicorn.hostsync`) compute
before their backward, the objectives' call (:class:`unicorn.objectives.Objectives`), with ``torch.compile`` in the
mode ``model.compile`` names. Those steps trace without a graph break, so each step kind is one forward graph (the
texture-averaging choice is a tensor input, selected on the device), and AOTAutograd derives its backward as one
graph; with ``reduce-overhead`` on CUDA both are captured as CUDA graphs and replayed, a step's thousands of kernels
launched by a few calls. The optimizer step (the fused Adam: one kernel per parameter group) and the checked first
iterations of a process run eagerly.

A CUDA graph replays on the addresses it was recorded with: the state a step changes besides the parameters (the
BatchNorm statistics, the neighbour memory, the sizes the rasterizers' fixed buffers needed) is written in place, so
each graph finds the same tensors at every call. A graph reuses its outputs' memory at its next replay: after each
call, the terms it returns and the render overflow counts are copied into memory of their own where graphs may
have captured them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from unicorn.model import Unicorn
from unicorn.model.compile import compile_options
from unicorn.objectives import Objectives
from unicorn.objectives.step_losses import StepLosses
from unicorn.render import OverflowCounter
from unicorn.render.overflow import note_overflow

__all__ = ["CUDA_GRAPH_MODES", "CompiledStep"]

#: the values of ``model.compile`` that capture CUDA graphs on CUDA devices
CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune", "cudagraphs")
#: graphs kept per step function: 2 step kinds x 4 stages, and a few buffer sizes each
_RECOMPILE_LIMIT = 64


class CompiledStep:
    """``objectives(kind, model, images, average_texture, iteration)`` compiled with ``torch.compile(mode=mode)``.

    Call it inside :func:`unicorn.hostsync.sync_free` (elsewhere the value checks' host reads break the graph).

    Args:
        objectives: the training objectives; model: the model they train.
        mode: a value of ``model.compile`` (:data:`unicorn.model.compile.COMPILE_OPTIONS`: a ``torch.compile`` mode,
            or ``"cudagraphs"``).
        backend: a ``torch.compile`` backend, in place of ``mode`` (None: inductor in ``mode``; ``"aot_eager"``
            traces and differentiates the same graphs without generating code, ``"cudagraphs"`` captures them with
            the eager kernels, as the tests do).
        copy_outputs: copy what outlives a step out of the graphs' memory after each call (None: where CUDA graphs
            capture, a mode of :data:`CUDA_GRAPH_MODES` or the ``"cudagraphs"`` backend, on a CUDA device).
    """

    def __init__(
        self,
        objectives: Objectives,
        model: Unicorn,
        mode: str = "default",
        backend: str | Callable[..., Any] | None = None,
        copy_outputs: bool | None = None,
    ) -> None:
        options: dict[str, Any] = compile_options(mode)  # checks the mode, with a backend too
        if backend is not None:
            options = {"backend": backend}
        self.objectives, self.model, self.mode, self.copy_outputs = objectives, model, mode, copy_outputs
        #: whether the graphs are captured as CUDA graphs where the step runs on CUDA
        self.captures = backend == "cudagraphs" if backend is not None else mode in CUDA_GRAPH_MODES
        self._compiled = torch.compile(self._forward, **options)
        # the texture-averaging choice as a 0-dim bool on the images' device, one per value and device: a tensor
        # input runs one graph for both choices (a Python bool is guarded on, a graph for each)
        self._average: dict[tuple[bool, torch.device], torch.Tensor] = {}
        # the renders' overflow counts inside the graphs, handed on to the caller's counter after each call (one
        # counter for every call: the graphs guard on the active counters)
        self._counter = OverflowCounter()

    def _forward(self, kind: str, images: torch.Tensor, average_texture: torch.Tensor, iteration: int) -> StepLosses:
        return self.objectives(kind, self.model, images, average_texture=average_texture, iteration=iteration)

    def __call__(self, kind: str, images: torch.Tensor, average_texture: bool, iteration: int) -> StepLosses:
        """The step's losses (:class:`~unicorn.objectives.step_losses.StepLosses`) on images (B, 3, S, S)."""
        copy = self.copy_outputs
        if copy is None:
            copy = self.captures and images.is_cuda
        if copy:
            torch.compiler.cudagraph_mark_step_begin()  # the previous step's graph outputs are no longer read
        key = (bool(average_texture), images.device)
        if key not in self._average:
            self._average[key] = torch.full((), key[0], device=images.device)  # made on the device: no copy
        with torch._dynamo.config.patch(recompile_limit=_RECOMPILE_LIMIT), self._counter:
            losses = self._compiled(kind, images, self._average[key], iteration)
        counts, self._counter.counts = self._counter.counts, {}
        for faces_per_pixel, (overflow, pixels) in counts.items():
            if copy and isinstance(overflow, torch.Tensor):
                overflow = overflow.clone()
            note_overflow(overflow, pixels, faces_per_pixel)
        if not copy:
            return losses
        terms = {k: v.clone() for k, v in losses.items()}
        return StepLosses(terms, losses.probs.clone(), {k: v.clone() for k, v in losses.stats.items()})
