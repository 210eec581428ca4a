"""The renderer's ``faces_per_pixel`` overflow during training: counted, logged as a share, said once per run.

During fit every render adds to an :class:`unicorn.render.OverflowCounter` instead of warning by itself; each
diagnostics check (:class:`unicorn.lit.CodeDiagnostics`) takes the share of the pixels rendered since the previous
check that had more candidate faces than ``faces_per_pixel`` (``render/overflow-share`` in ``diagnostics.csv`` and
the loggers), and the first check that finds any warns, with that share and the setting to raise. Without the
diagnostics (``callbacks.diagnostics=null``), the steps without host reads count their own renders
(:class:`unicorn.lit.UnicornLitModule`): a render's own warning would read its count back at every render. Their
deferred reads (the logging steps, a checkpoint) take the share, and the first that finds any warns.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from typing import Any

from unicorn.render import OverflowCounter, RenderOverflowWarning

__all__ = ["TrainingOverflow"]


_FOLLOWED = "diagnostics.csv and the loggers follow the share (render/overflow-share); "


class TrainingOverflow:
    """The renders of one training run, counted between :meth:`start` and :meth:`stop`.

    The counts come from the rasterizer's own host read (``Fragments.overflow``), or stay on the device in the steps
    without host reads until :meth:`share` takes them: counting adds no device synchronisation to a training step.
    Renders in other threads, and those made inside another active :class:`~unicorn.render.OverflowCounter` (the
    diagnostics' own, :meth:`CodeDiagnostics.check <unicorn.lit.CodeDiagnostics.check>`), are not counted here.
    """

    def __init__(self, logged: bool = True) -> None:
        self.counter = OverflowCounter()
        self.since: int | None = None  # the iteration of the previous share
        self.warned = False  # once per run
        self.logged = logged  # whether the shares are logged (the warning says where)

    def state_dict(self) -> dict[str, Any]:
        """The counts since the previous share and whether the run warned: a resumed run's shares and its one
        warning are those of an uninterrupted run."""
        counts = {int(k): [int(over), int(rendered)] for k, (over, rendered) in self.counter.counts.items()}
        return {"counts": counts, "since": self.since, "warned": self.warned}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.counter.counts = {int(k): (int(over), int(rendered)) for k, (over, rendered) in state["counts"].items()}
        self.since, self.warned = state["since"], bool(state["warned"])

    def start(self, step: int) -> None:
        """Count every render of this thread from iteration ``step`` on (a restored run goes on from its state)."""
        if self.since is None:
            self.since = int(step)
        self.counter.start()

    def stop(self) -> None:
        """Stop counting (the renders warn by themselves again)."""
        self.counter.stop()

    @contextlib.contextmanager
    def counting(self, step: int) -> Iterator[None]:
        """Count the renders of the block, from iteration ``step`` on (:meth:`start`, :meth:`stop`)."""
        self.start(step)
        try:
            yield
        finally:
            self.stop()

    def share(self, step: int) -> float:
        """The share of the pixels rendered since the previous call that overflowed ``faces_per_pixel`` (NaN when
        nothing was rendered); the first call that finds any emits a :class:`RenderOverflowWarning`."""
        counts, since = self.counter.take(), self.since if self.since is not None else 0
        self.since = int(step)
        if counts.overflow and not self.warned:
            self.warned = True
            K = counts.faces_per_pixel
            warnings.warn(
                f"renderer: in the training renders of iterations {since}-{step}, {counts.describe()}. If that "
                f"matters, train with renderer.faces_per_pixel=N above {K} (e.g. {2 * K}; memory and time grow "
                f"with it). {_FOLLOWED if self.logged else ''}said once per run",
                RenderOverflowWarning,
                stacklevel=2,
            )
        return counts.share
