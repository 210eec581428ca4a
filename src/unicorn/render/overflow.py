"""Pixels whose farthest candidate faces the rasterizer dropped (more candidates than ``faces_per_pixel``).

Every rasterization reports its count here (:func:`note_overflow`; the count of one render is also
``Fragments.overflow``). What happens to it depends on the caller:

- by default (a library call) the first render that overflows with a given ``faces_per_pixel`` warns once per
  process, with a :class:`RenderOverflowWarning`;
- inside ``with OverflowCounter() as counter:`` nothing is printed: the renders of the block add their counts to
  the counter, and the caller says what it means where it can (training's diagnostics log the share of pixels and
  warn once per run; ``unicorn-reconstruct`` and ``unicorn-eval`` say it once per command).

Counting costs no device synchronisation of its own: the rasterizer reads the count in the host read it makes
anyway (the packed layout's size, see :mod:`unicorn.render.raster`). The rasterizer without host reads
(:mod:`unicorn.render.fixed`) reports a count on the device: a counter adds it up there and reads the sum when it is
taken (:meth:`OverflowCounter.take`), on the logging steps of training. Outside any counter such a render inside
:func:`unicorn.hostsync.sync_free` does not warn, which would read the count: ``Fragments.overflow`` keeps it.
"""

from __future__ import annotations

import sys
import warnings
from contextvars import ContextVar
from dataclasses import dataclass, field
from types import TracebackType

import torch

from unicorn.errors import UnicornWarning
from unicorn.hostsync import is_sync_free

__all__ = ["OverflowCounter", "RenderOverflowWarning", "counting", "note_overflow"]

#: the counters collecting renders, innermost last (per thread and asyncio task)
_ACTIVE: ContextVar[tuple[OverflowCounter, ...]] = ContextVar("unicorn_render_overflow", default=())
#: the same as a global that torch.compile traces (it cannot read a context variable): the last set in any thread
_TRACED: tuple[OverflowCounter, ...] = ()
#: the faces_per_pixel settings whose overflow was already reported in this process (outside any counter)
_WARNED: set[int] = set()


class RenderOverflowWarning(UnicornWarning):
    """Some pixels had more candidate faces than ``faces_per_pixel``; the farthest were dropped."""


@dataclass
class OverflowCounter:
    """Counts of pixels that overflowed ``faces_per_pixel``, and of the pixels rendered, per setting, over renders.

    As a context manager (or between :meth:`start` and :meth:`stop`), it collects every rasterization of its block
    in place of the :class:`RenderOverflowWarning`. Blocks nest: a render counts in the innermost active counter
    only. The active counters are per thread (a :class:`contextvars.ContextVar`): renders in another thread warn as
    usual.

    Attributes:
        counts: ``faces_per_pixel`` -> (pixels that had more candidate faces than that, pixels rendered with it),
            at the raster's (supersampled) size: ``B x H x W`` pixels per render.
    """

    counts: dict[int, tuple[int, int]] = field(default_factory=dict)

    def add(self, overflow: int | torch.Tensor, pixels: int, faces_per_pixel: int) -> None:
        """Count one render: ``overflow`` of its ``pixels`` pixels had more than ``faces_per_pixel`` candidates (a
        0-dim tensor is summed where it is, and read by :meth:`take`)."""
        before, rendered = self.counts.get(int(faces_per_pixel), (0, 0))
        over = overflow.detach() if isinstance(overflow, torch.Tensor) else int(overflow)
        self.counts[int(faces_per_pixel)] = (before + over, rendered + int(pixels))

    @property
    def overflow(self) -> int:
        """Pixels that overflowed, over every setting."""
        return sum(over for over, _ in self.counts.values())

    @property
    def pixels(self) -> int:
        """Pixels rendered, over every setting."""
        return sum(rendered for _, rendered in self.counts.values())

    @property
    def faces_per_pixel(self) -> int:
        """The largest setting whose renders overflowed; 0 when none did."""
        return max((k for k, (over, _) in self.counts.items() if over), default=0)

    @property
    def share(self) -> float:
        """The share of the pixels that overflowed among those rendered with the settings that overflowed (renders
        with another setting, e.g. hard ones with one face per pixel, do not dilute it); 0 when none overflowed, NaN
        when nothing was rendered."""
        hit = [(over, rendered) for over, rendered in self.counts.values() if over]
        if not hit:
            return 0.0 if self.pixels else float("nan")
        return sum(over for over, _ in hit) / sum(rendered for _, rendered in hit)

    def take(self) -> OverflowCounter:
        """The counts so far, as a new counter; this one starts again from zero (and stays active if it was)."""
        counts, self.counts = self.counts, {}
        return OverflowCounter({k: (int(over), rendered) for k, (over, rendered) in counts.items()})

    def describe(self) -> str:
        """``"<share> of the <N> pixels rendered with faces_per_pixel=<K> had more candidate faces ..."``, for each
        setting that overflowed (empty when none did)."""
        return "; ".join(
            f"{_percent(over / rendered)} of the {rendered:,} pixels rendered with faces_per_pixel={k} had more "
            "candidate faces within the blur radius, and lost their farthest ones"
            for k, (over, rendered) in sorted(self.counts.items())
            if over
        )

    def start(self) -> OverflowCounter:
        """Collect the renders from now on (until :meth:`stop`), innermost of the active counters."""
        _set_active((*_ACTIVE.get(), self))
        return self

    def stop(self) -> None:
        """Stop collecting (the innermost activation of this counter; nothing if it is not active)."""
        active = list(_ACTIVE.get())
        for i in range(len(active) - 1, -1, -1):
            if active[i] is self:
                del active[i]
                _set_active(tuple(active))
                return

    def __enter__(self) -> OverflowCounter:
        return self.start()

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, traceback: TracebackType | None
    ) -> None:
        self.stop()


def _set_active(counters: tuple[OverflowCounter, ...]) -> None:
    global _TRACED
    _ACTIVE.set(counters)
    _TRACED = counters


def _active() -> tuple[OverflowCounter, ...]:
    """The active counters, innermost last (their mirror while torch.compile traces: it cannot read a ContextVar)."""
    return _TRACED if torch.compiler.is_compiling() else _ACTIVE.get()


def counting() -> bool:
    """Whether a render in this thread now counts in an active :class:`OverflowCounter` instead of warning."""
    return bool(_active())


#: the modules a warning about a render does not point into: the renderer's own and torch's (``nn.Module`` calls)
_INNER_MODULES = ("unicorn.render.", "torch.")


def _caller_level() -> int:
    """The ``stacklevel`` of the first frame, up from the caller of this function, outside :data:`_INNER_MODULES`:
    the line of the user's that asked for the render."""
    frame, level = sys._getframe(2), 2
    while frame.f_back is not None and str(frame.f_globals.get("__name__", "")).startswith(_INNER_MODULES):
        frame, level = frame.f_back, level + 1
    return level


def note_overflow(overflow: int | torch.Tensor, pixels: int, faces_per_pixel: int) -> None:
    """Report one render: to the innermost active :class:`OverflowCounter`, else (when ``overflow`` > 0) as a
    :class:`RenderOverflowWarning`, once per ``faces_per_pixel`` setting and process, except with one face per
    pixel (``faces_per_pixel=1``), whose renders keep the nearest face by design. A count on the device (a 0-dim
    tensor, from the fixed buffers) inside :func:`unicorn.hostsync.sync_free` and outside any counter is not
    reported: reading it would be the host read that block leaves out (``Fragments.overflow`` keeps it).

    Python's own once-per-location registry is reset whenever any library changes the warning filters (Lightning
    does, every step), which would repeat the line thousands of times; hence the set kept here. Called by
    :func:`~unicorn.render.raster.rasterize_meshes`; the warning points at the first line outside the renderer
    and torch that asked for the render.
    """
    active = _active()
    if active:
        active[-1].add(overflow, pixels, faces_per_pixel)
        return
    if isinstance(overflow, torch.Tensor) and is_sync_free():
        return  # `not overflow` would read the device back, and break a torch.compile graph
    if not overflow or faces_per_pixel == 1 or faces_per_pixel in _WARNED:
        return
    _WARNED.add(faces_per_pixel)
    warnings.warn(
        f"some pixels had more than faces_per_pixel={faces_per_pixel} candidate faces and the farthest were "
        f"dropped ({_percent(overflow / max(pixels, 1))} of this render's {pixels:,} pixels; said once per setting: "
        "Fragments.overflow counts every render, unicorn.render.OverflowCounter collects them without this "
        "warning; raise faces_per_pixel if it matters)",
        RenderOverflowWarning,
        stacklevel=_caller_level(),
    )


def _percent(share: float) -> str:
    """A share as a percentage: two significant digits below 10 % (``"0.031%"``), whole ones above (``"12%"``)."""
    percent = 100 * share
    return f"{percent:.2g}%" if percent < 10 else f"{percent:.0f}%"
