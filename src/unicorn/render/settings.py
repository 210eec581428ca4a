"""The renderer's settings in one object, in PyTorch3D's manner (its ``RasterizationSettings`` and ``BlendParams``
together): every option of the built-in backends, its default and its range, defined and checked here.

The backends (:mod:`unicorn.render.backends`) take these options as keywords and keep them as
``renderer.settings``; :class:`~unicorn.render.MeshRasterizer` checks its own through :func:`check_render_option`,
and so does the training configuration's ``renderer`` group before anything is built.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from ..geometry.cameras import image_hw
from .raster import RenderError, check_whole_number, is_real

__all__ = ["BACKGROUND_COLOR", "DEFAULT_SETTINGS", "RenderSettings", "buffer_color", "check_render_option"]

#: the colour behind the mesh where no background image is given: white, as the reference renders
BACKGROUND_COLOR: tuple[float, float, float] = (1.0, 1.0, 1.0)

#: the lowest value of each numeric setting (a finite number, None allowed for ``max_bytes``: the default limit)
_LOWEST = {"sigma": 0, "gamma": 0, "eps": 0, "faces_per_pixel": 1, "supersample": 1, "max_candidates": 1}
#: the settings that must lie above their lowest value, not at it (SoftRas divides by gamma)
_ABOVE = ("gamma",)
#: the settings that count something: whole numbers (2.0 is 2; 2.5 is an error, not 2)
_WHOLE = ("faces_per_pixel", "supersample", "max_candidates", "max_bytes")


@dataclass(frozen=True)
class RenderSettings:
    """The options of a renderer backend, checked when made (each backend reads the ones it uses).

    Attributes:
        image_size: (H, W) of the images (an int H is made (H, H)).
        sigma: occupancy temperature on squared NDC distances (1e-4 in the reference); the blur radius follows from
            it. 0 renders hard edges (the layered backend; SoftRas needs > 0).
        gamma: SoftRas' depth softmax temperature (> 0).
        faces_per_pixel: K, the most faces kept per pixel (25 for real images, 50 for ShapeNet in the reference).
        eps: normalised inverse depth of SoftRas' background layer.
        supersample: integer supersampling factor of the hard backend (1 = none).
        background_color: colour (C,) behind the mesh where no background image is given.
        max_candidates: rasterizer work budget per chunk of images (bounds memory).
        max_bytes: refuse renders whose fragments could exceed this many bytes (None: ``$UNICORN_MAX_RENDER_BYTES``
            or 16 GiB; 0: no limit).
        perspective_correct: perspective-correct barycentrics (PyTorch3D's option of that name) instead of
            screen-space ones.

    Raises:
        RenderError: a value out of its range (named, see :func:`check_render_option`).
    """

    image_size: int | Sequence[int] = 64
    sigma: float = 1e-4
    gamma: float = 1e-4
    faces_per_pixel: int = 25
    eps: float = 1e-3
    supersample: int = 2
    background_color: Sequence[float] = BACKGROUND_COLOR
    max_candidates: int = 1 << 23
    max_bytes: int | None = None
    perspective_correct: bool = False

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            check_render_option(f.name, getattr(self, f.name))
        # frozen: set the normalised forms through object
        object.__setattr__(self, "image_size", image_hw(self.image_size))  # type: ignore[arg-type]
        object.__setattr__(self, "background_color", tuple(float(c) for c in self.background_color))
        for name in _LOWEST:  # Python numbers (a NumPy scalar is accepted, and kept out of saved configurations)
            value = getattr(self, name)
            object.__setattr__(self, name, int(value) if name in _WHOLE else float(value))
        if self.max_bytes is not None:
            object.__setattr__(self, "max_bytes", int(self.max_bytes))


def check_render_option(name: str, value: Any) -> None:
    """Check one setting of :class:`RenderSettings` against its range; other names pass.

    Raises:
        RenderError: the message names the setting, its range and the value (``image_size``: as
            :func:`unicorn.checks.check_image_size`).
    """
    if name == "image_size":
        image_hw(value)
    elif name in _LOWEST or (name == "max_bytes" and value is not None):
        low, above = _LOWEST.get(name, 0), name in _ABOVE
        ok = is_real(value) and math.isfinite(value)
        ok = ok and (value > low if above else value >= low)
        if name in _WHOLE:
            check_whole_number(name, value, low)
        if not ok:
            raise RenderError(f"{name} must be a finite number {'>' if above else '>='} {low}, got {value!r}")
    elif name == "perspective_correct" and not isinstance(value, bool):
        raise RenderError(f"perspective_correct must be True or False, got {value!r}")
    elif name == "background_color" and not _finite_numbers(value):
        raise RenderError(f"background_color must be one finite number per channel, got {value!r}")


def _finite_numbers(value: Any) -> bool:
    """Whether ``value`` is a non-empty sequence of finite numbers (a 1-D tensor included)."""
    if isinstance(value, str | bytes):
        return False
    try:
        numbers = [float(c) for c in value]
    except (TypeError, ValueError, RuntimeError):
        return False
    return len(numbers) > 0 and all(math.isfinite(c) for c in numbers)


#: the defaults, for the backends' signatures
DEFAULT_SETTINGS = RenderSettings()


def buffer_color(buffer: torch.Tensor, given: Sequence[float]) -> tuple[float, ...]:
    """The colour a renderer's ``background_color`` buffer (C,) holds, as numbers: ``given`` where the buffer holds
    it in the buffer's dtype, else per channel the number of fewest decimals that the dtype rounds to the buffer's
    value (0.1, not its float32 rounding 0.10000000149...). One host read."""
    values = buffer.detach().cpu()
    if len(given) == values.numel() and torch.equal(values, torch.tensor(list(given), dtype=values.dtype)):
        return tuple(given)
    return tuple(_shortest_decimal(v) for v in values)


def _shortest_decimal(value: torch.Tensor) -> float:
    """The number of fewest decimals that rounds to ``value`` (a 0-dim floating-point tensor) in its dtype."""
    for digits in range(1, 18):
        candidate = round(float(value), digits)
        if torch.tensor(candidate, dtype=value.dtype) == value:
            return candidate
    return float(value)
