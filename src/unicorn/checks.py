"""Input checks shared by the renderer, the metrics and the evaluation (the ground floor: torch only).

Each check raises one error naming the argument and what is wrong with it: ``TypeError`` for a wrong type or
dtype, :class:`ShapeError` (a ``ValueError``) for a shape outside its contract (:func:`check_shape`), ``ValueError``
for a wrong value, :class:`FaceIndexError` (an ``IndexError`` and a ``ValueError``) for face indices outside the
vertices.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from collections.abc import Mapping, Sequence
from numbers import Integral

import torch

from unicorn.caching import cache_outside_compile
from unicorn.errors import UserError
from unicorn.hostsync import is_sync_free

__all__ = [
    "FACE_DTYPES",
    "MAX_SEED",
    "Dims",
    "EnvironmentLimitError",
    "FaceIndexError",
    "NonFiniteValueError",
    "ShapeError",
    "SizeLimitError",
    "check_shape",
    "check_faces",
    "check_image_size",
    "check_mesh",
    "check_normals",
    "check_pixels",
    "check_points",
    "check_rotations",
    "check_same_batch",
    "check_same_dtype",
    "check_limit",
    "check_translations",
    "env_limit",
    "is_number",
    "is_real",
    "is_seed",
    "is_whole",
]

#: the largest seed: numpy's seeds are whole numbers in [0, 2**32 - 1]
MAX_SEED = 2**32 - 1


def is_whole(value: object) -> bool:
    """Whether ``value`` is a Python int, not a bool (which Python counts as one)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value: object) -> bool:
    """Whether ``value`` is a real number, a NumPy scalar included, but not a bool (which Python counts as one)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def is_number(value: object) -> bool:
    """Whether ``value`` is a finite Python int or float, not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def is_seed(value: object) -> bool:
    """Whether ``value`` is a seed numpy takes: a whole number in [0, :data:`MAX_SEED`]."""
    return is_whole(value) and 0 <= value <= MAX_SEED


class NonFiniteValueError(ValueError):
    """An input holds NaN or infinite values (the message names it)."""


class FaceIndexError(IndexError, ValueError):
    """Face indices outside ``[0, V)``: an index error, and a bad value of the argument."""


class EnvironmentLimitError(UserError, ValueError):
    """A size limit in the environment (``UNICORN_MAX_*``) that is not a whole number >= 0."""


def env_limit(name: str, default: int, unit: str) -> int | None:
    """The size limit the environment variable ``name`` sets: ``default`` when it is unset or empty, None (no
    limit) for 0; ``1e9`` is read as 1000000000.

    Raises:
        EnvironmentLimitError: a value that is not a finite number >= 0 (the message names the variable).
    """
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise EnvironmentLimitError(f"{name}={text!r} is not a number of {unit} >= 0 (0: no limit)")
    return int(value) or None


class SizeLimitError(UserError, ValueError):
    """A size asked for (an option, a setting) whose allocation would exceed a limit, refused before it is made."""


def check_limit(
    setting: str,
    what: str,
    amount: int,
    limit: int | None,
    unit: str,
    source: str,
    error: type[SizeLimitError] = SizeLimitError,
) -> None:
    """Refuse ``amount`` ``unit`` above ``limit`` before anything is allocated: the one bound of every size a
    command is asked for (image sides, texture sizes, pictures, model widths, points, steps).

    Args:
        setting: the option or config key with its value, as the user gave it (``"--turntable-frames 1000000"``).
        what: what the amount is (``"frames of 48 x 48 float32 RGBA"``).
        amount: how much of ``unit`` the setting asks for.
        limit: the most allowed; None: no limit.
        unit: ``"bytes"``, ``"parameters"``, ``"points"``...
        source: where the limit comes from: the environment variable that sets it (``"UNICORN_MAX_IMAGE_BYTES;
            0: no limit"``), or the documented maximum.
        error: the class raised, :class:`SizeLimitError` or a subclass.

    Raises:
        SizeLimitError: ``amount > limit``, in one line: ``<setting> needs <amount> <unit> (<what>), above the limit
            of <limit> <unit> (<source>)``.
    """
    if limit is not None and amount > limit:
        raise error(f"{setting} needs {amount:,} {unit} ({what}), above the limit of {limit:,} {unit} ({source})")


class ShapeError(ValueError):
    """A tensor whose shape does not match its contract (a ``ValueError``, as a bad argument value)."""


_DIM = re.compile(r"^(\*[A-Za-z_][A-Za-z0-9_]*|\*|\d+|[A-Za-z_][A-Za-z0-9_]*)$")
#: a contract's bindings: a name's size, or a named ``*`` group's sizes
Dims = dict[str, "int | tuple[int, ...]"]


@cache_outside_compile(maxsize=512)  # traced by torch.compile, the parse is run
def _parse_shape(shape: str) -> tuple[tuple[str, ...], ...]:
    """``"B, V, 3"`` or ``"B V 3"`` -> ``(("B", "V", "3"),)``; alternatives are separated by ``|``; ``*`` or
    ``*name`` (first only) stands for any leading dimensions."""
    alternatives = tuple(tuple(alt.replace(",", " ").split()) for alt in shape.split("|"))
    for tokens in alternatives:
        if not tokens or not all(_DIM.match(t) for t in tokens) or any(t.startswith("*") for t in tokens[1:]):
            raise ValueError(f"bad shape contract {shape!r}: use names, integers and a leading '*' or '*name'")
    return alternatives


def _match(tokens: tuple[str, ...], actual: tuple[int, ...], bound: Dims) -> Dims | None:
    """The new bindings of ``actual`` under one contract, or None when it does not match."""
    lead = tokens[0] if tokens[0].startswith("*") else None
    fixed = tokens[1:] if lead else tokens
    if len(actual) < len(fixed) or (lead is None and len(actual) != len(fixed)):
        return None
    new: Dims = {}
    if lead is not None and lead != "*":
        sizes = actual[: len(actual) - len(fixed)]
        if bound.get(lead[1:], sizes) != sizes:
            return None
        new[lead[1:]] = sizes
    for token, size in zip(fixed, actual[len(actual) - len(fixed) :]):
        want = int(token) if token.isdigit() else bound.get(token, new.get(token))
        if want is not None and want != size:
            return None
        if not token.isdigit():
            new[token] = size
    return new


def _describe(tokens: tuple[str, ...], bound: Dims) -> str:
    """One contract with the sizes already known: ``("B", "V", "3")``, ``{"B": 4}`` -> ``"(4, V, 3)"``."""
    parts = []
    for t in tokens:
        value = bound.get(t.lstrip("*"), t) if t != "*" else "..."
        if isinstance(value, tuple):
            parts.extend(map(str, value))
        else:
            parts.append("..." if isinstance(value, str) and value.startswith("*") else str(value))
    return f"({parts[0]},)" if len(parts) == 1 else f"({', '.join(parts)})"  # as Python prints the shape


def check_shape(x: object, shape: str, name: str, dims: Dims | None = None, *, floating: bool = False) -> Dims:
    """Check that ``x`` is a tensor of the contracted shape; returns the sizes bound to the symbolic dimensions.

    Args:
        x: the value to check.
        shape: the contract, e.g. ``"B, V, 3"``: an integer is an exact size, a name is any size but the same
            wherever the name recurs (within ``x`` and across the calls sharing ``dims``), and a leading ``*``
            stands for any number of leading dimensions (``"*, 3, 3"``); a leading ``*name`` binds them as a
            group (``"*N, 2"`` then ``"*N"``: the same leading sizes). Alternatives are separated by ``|``
            (``"B, H, W | B, 1, H, W"``); the first that matches binds.
        name: the argument's name, for the error.
        dims: sizes already bound (``{"B": 4}``; a ``*name`` group as a tuple); updated in place with the new
            bindings.
        floating: also require a floating point dtype.

    Raises:
        TypeError: ``x`` is not a tensor, or not floating point when ``floating``.
        ShapeError: the shape does not match (the message states the contract with the sizes already known).
    """
    alternatives = _parse_shape(shape)
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    bound = {} if dims is None else dims
    actual = tuple(x.shape)
    for tokens in alternatives:
        new = _match(tokens, actual, bound)
        if new is not None:
            break
    else:
        expected = " or ".join(_describe(tokens, bound) for tokens in alternatives)
        raise ShapeError(f"{name} must have shape {expected}, got {actual}")
    if floating and not x.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {x.dtype}")
    bound.update(new)
    return bound


def check_points(x: torch.Tensor, name: str, dim: int | None = 3) -> torch.Tensor:
    """Check a batched cloud ``(B, N, D)``: floating point, non-empty, finite shape; returns it unchanged."""
    check_shape(x, f"B, N, {dim or 'D'}", name, floating=True)
    if x.shape[0] == 0:
        raise ShapeError(f"{name} has an empty batch dimension")
    if x.shape[1] == 0:
        raise ShapeError(f"{name} is an empty point cloud (N = 0)")
    return x


def check_same_batch(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Batch sizes and devices of two tensors must match."""
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"batch sizes differ: {name_a} has {a.shape[0]}, {name_b} has {b.shape[0]}")
    if a.device != b.device:
        raise ValueError(f"{name_a} is on {a.device} but {name_b} is on {b.device}")


def check_same_dtype(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Two tensors computed together must share a dtype: no silent promotion (PyTorch3D does not promote either)."""
    if a.dtype != b.dtype:
        raise TypeError(f"{name_a} is {a.dtype} but {name_b} is {b.dtype}: give both the same dtype")


def check_image_size(image_size: object, name: str = "image_size") -> tuple[int, int]:
    """``(H, W)`` from a positive int or a pair of them; anything else (a float, a string, a bool) is an error.

    Raises:
        TypeError: not an int or a pair of ints.
        ValueError: a pair of another length, or a side <= 0.
    """

    def is_int(v: object) -> bool:
        return isinstance(v, Integral) and not isinstance(v, bool)  # True is an int to Python, not a size

    hw = (image_size, image_size) if is_int(image_size) else image_size
    if not isinstance(hw, Sequence) or isinstance(hw, (str, bytes)) or not all(is_int(s) for s in hw):
        raise TypeError(f"{name} must be a positive int or (H, W) of ints, got {image_size!r}")
    if len(hw) != 2 or min(hw) <= 0:
        raise ValueError(f"{name} must be a positive int or (H, W), got {image_size!r}")
    return int(hw[0]), int(hw[1])


def check_normals(normals: torch.Tensor | None, points: torch.Tensor, name: str) -> None:
    """Normals, when given, must have the shape of their points."""
    if normals is None:
        return
    if not isinstance(normals, torch.Tensor) or normals.shape != points.shape:
        shape = tuple(normals.shape) if isinstance(normals, torch.Tensor) else type(normals).__name__
        raise ValueError(f"{name} must have the shape of its points {tuple(points.shape)}, got {shape}")
    if not normals.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {normals.dtype}")


#: how far beyond [0, 1] a pixel may lie (the rounding of a resampled image)
PIXEL_TOLERANCE = 1e-3


def check_pixels(images: torch.Tensor, name: str = "images") -> None:
    """Every value of ``images`` must be a pixel in [0, 1]: a float image in [0, 255], or one normalised with a mean
    and a standard deviation, reads as garbage to a model trained on [0, 1]. Reads the range: one device sync.

    Raises:
        ValueError: a value out of [0, 1] (beyond :data:`PIXEL_TOLERANCE`), NaN or infinite; names the range.
    """
    if images.numel() == 0:
        return
    lo, hi = (float(v) for v in torch.aminmax(images.detach()))
    if lo >= -PIXEL_TOLERANCE and hi <= 1 + PIXEL_TOLERANCE:
        return
    if not math.isfinite(lo) or not math.isfinite(hi):
        raise NonFiniteValueError(f"{name} hold NaN or infinite values; pixels must be in [0, 1]")
    hint = " (pixels in [0, 255]: divide by 255)" if lo >= -PIXEL_TOLERANCE and hi <= 255 + PIXEL_TOLERANCE else ""
    raise ValueError(f"{name} must hold pixels in [0, 1], got values in [{lo:.4g}, {hi:.4g}]{hint}")


def check_rotations(R: torch.Tensor, name: str, batch: int | None = None) -> None:
    """``R`` must be ``(B, 3, 3)`` floating point, with ``B == batch`` when given."""
    check_shape(R, "B, 3, 3", name, {} if batch is None else {"B": batch}, floating=True)


def check_translations(T: torch.Tensor, name: str, batch: int) -> None:
    """``T`` must be ``(B, 3)`` floating point with ``B == batch``."""
    check_shape(T, "B, 3", name, {"B": batch}, floating=True)


def _all_finite(t: torch.Tensor) -> torch.Tensor:
    """0-dim bool on ``t``'s device: every value finite. ``(t * 0).sum()`` is exactly 0 then, and NaN when any value
    is NaN or infinite; on CPU it is much cheaper than ``isfinite(t).all()`` (``docs/performance.md``)."""
    return torch.isfinite((t.detach() * 0).sum())


#: the integer dtypes torch indexes with (its unsigned 16-, 32- and 64-bit types have no min, max or gather)
FACE_DTYPES = (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8)


def _check_face_layout(faces: torch.Tensor, allow_empty: bool) -> None:
    check_shape(faces, "F, 3", "faces")
    if faces.dtype not in FACE_DTYPES:
        names = ", ".join(str(d).removeprefix("torch.") for d in FACE_DTYPES)
        raise TypeError(f"faces must be an integer tensor of {names} (faces.long() converts), got {faces.dtype}")
    if faces.shape[0] == 0 and not allow_empty:
        raise ValueError("faces is empty (F = 0)")


def _check_face_range(lo: int, hi: int, num_verts: int) -> None:
    if lo < 0 or hi >= num_verts:
        raise FaceIndexError(f"face indices must be in [0, {num_verts}), got range [{lo}, {hi}]")


def check_faces(faces: torch.Tensor, num_verts: int, *, allow_empty: bool = False) -> None:
    """Faces ``(F, 3)`` of any integer dtype indexing ``num_verts`` vertices (one host sync when F > 0; the range
    is not read inside :func:`unicorn.hostsync.sync_free`)."""
    _check_face_layout(faces, allow_empty)
    if faces.numel() and not is_sync_free():
        _check_face_range(*torch.stack([faces.min(), faces.max()]).tolist(), num_verts)


def check_mesh(
    verts: torch.Tensor,
    faces: torch.Tensor,
    *,
    allow_empty: bool = False,
    finite: bool = False,
    finite_also: Mapping[str, torch.Tensor] | None = None,
) -> None:
    """Batched vertices ``(B, V, 3)`` float and shared faces ``(F, 3)`` integer indexing them, on one device.

    Args:
        verts: (B, V, 3) float32 or float64.
        faces: (F, 3) integer.
        allow_empty: accept B = 0, V = 0 or F = 0 (the renderer draws nothing); otherwise each is an error.
        finite: also require finite vertices.
        finite_also: other tensors, by argument name, that must be finite (a renderer's colours), checked in
            the same read; they must be on the vertices' device.

    The value checks (face range, finiteness) are reduced on the device and read back together: one host sync,
    skipped inside :func:`unicorn.hostsync.sync_free` (shapes, dtypes and devices are checked there too).
    """
    if allow_empty:
        check_shape(verts, "B, V, 3", "verts")
    else:
        check_points(verts, "verts")
    if verts.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"verts must be float32 or float64, got {verts.dtype}")
    _check_face_layout(faces, allow_empty)
    if faces.device != verts.device:
        raise ValueError(f"verts is on {verts.device} but faces is on {faces.device}")
    for name, t in (finite_also or {}).items():  # computed with the vertices: no silent copy between devices
        if t.device != verts.device:
            raise ValueError(f"verts is on {verts.device} but {name} is on {t.device}")
    if is_sync_free():
        return
    if verts.is_meta:  # (renders without host reads trace on it: they read no value)
        raise ValueError("verts is a meta tensor, which holds no values to check: render it inside sync_free()")
    values = [faces.min(), faces.max()] if faces.numel() else []
    named = {"verts": verts} if finite else {}
    named.update(finite_also or {})
    values += [_all_finite(t).to(torch.int64) for t in named.values()]
    if not values:
        return
    read = torch.stack([v.to(device=verts.device, dtype=torch.int64) for v in values]).tolist()
    if faces.numel():
        _check_face_range(read[0], read[1], verts.shape[1])
    for name, ok in zip(named, read[len(read) - len(named) :]):
        if not ok:
            raise NonFiniteValueError(f"{name} contains NaN or infinite values")
