"""Soft top-K mesh rasterization in pure PyTorch (CPU and CUDA).

Two stages, so that neither the memory nor the gradient path ever touches a (B, H, W, F) tensor:

1. Selection, without gradient (:mod:`unicorn.render.selection`). Every face enumerates the pixel centres of its
   2D bounding box grown by the blur radius (``repeat_interleave`` over per-face box sizes); an exact test keeps
   the pixels the face contains or passes within the blur radius of; one sort on a (pixel, depth) key ranks the
   faces of each pixel and the nearest ``faces_per_pixel`` are kept. Cost: O(sum of box areas + P log P),
   chunked over images.
2. Recomputation, with gradient (here). For the kept pairs only, barycentrics, signed distances and depth are
   recomputed from the vertices with ordinary torch ops, so autograd carries gradients to vertex positions.

Which faces are kept changes only where their occupancy is below the blur threshold, so treating selection
as piecewise constant leaves the image continuous up to that threshold.

Units: distances are *squared* NDC distances as in PyTorch3D and the UNICORN reference; ``blur_radius`` is a
squared NDC distance too. See :func:`blur_radius_from_sigma`.

Memory: a render is refused before anything is allocated when its fragments could exceed
:func:`max_render_bytes` (16 GiB unless ``UNICORN_MAX_RENDER_BYTES`` or the ``max_bytes`` argument says otherwise):
``B x H x W x K x 64`` bytes, the packed pairs if every pixel of the (supersampled) raster kept
``faces_per_pixel = K`` faces; see :func:`check_render_size`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any

import torch

from ..checks import (
    NonFiniteValueError,
    SizeLimitError,
    check_mesh,
    check_rotations,
    check_translations,
    env_limit,
    is_real,
)
from ..errors import UserError
from ..geometry.cameras import image_hw, ndc_to_pixel
from ..hostsync import is_sync_free
from .fixed import select_fixed
from .fragments import Fragments
from .overflow import note_overflow
from .selection import Selection, select_pairs
from .triangles import barycentric_and_distance, clip_barycentric, perspective_correct_barycentric

__all__ = [
    "DEFAULT_MAX_RENDER_BYTES",
    "MAX_RENDER_BYTES_ENV",
    "PAIR_BYTES",
    "RenderError",
    "RenderSizeError",
    "blur_radius_from_sigma",
    "check_mesh_inputs",
    "check_pose_inputs",
    "check_render_size",
    "max_render_bytes",
    "rasterize_meshes",
]

#: bytes of one packed (pixel, face) pair, rounded up: four int64 indices, the inside flag, and barycentrics,
#: distance and depth in float32 (53 bytes); autograd and the aggregators keep a few times that while rendering
PAIR_BYTES = 64
#: the bytes one candidate pair (a face against a pixel of its box) can take while the pairs are ranked: the
#: indices, distances, depths and masks that :func:`~unicorn.render.selection.select_pairs` holds together
CANDIDATE_BYTES = 128
#: the largest fragments a render may need, ``B x H x W x K x PAIR_BYTES``: 16 GiB (a batch of 192 training
#: images of 64 x 64 with K = 25 needs at most 1.3 GB; a single 10000 x 10000 render with K = 25, 160 GB)
DEFAULT_MAX_RENDER_BYTES = 16 << 30
#: environment variable holding that limit; 0 means no limit
MAX_RENDER_BYTES_ENV = "UNICORN_MAX_RENDER_BYTES"


class RenderError(UserError, ValueError):
    """A renderer setting that cannot be used (a bad ``sigma``, ``faces_per_pixel``, ``supersample``, background
    colour...): a mistake in what was asked for, named in the message; still a ``ValueError``."""


def check_blur_radius(blur_radius: Any) -> None:
    """Raise :class:`RenderError` unless ``blur_radius`` is a finite number >= 0 (a one-element tensor included; a
    string, a bool or None is not)."""
    try:
        value = None if isinstance(blur_radius, str | bytes | bool) else float(blur_radius)
    except (TypeError, ValueError, RuntimeError):
        value = None
    if value is None or not (math.isfinite(value) and value >= 0):
        raise RenderError(f"blur_radius must be a finite number >= 0, got {blur_radius!r}")


class RenderSizeError(RenderError, SizeLimitError):
    """A render whose fragments could exceed the memory limit (:func:`check_render_size`)."""


def max_render_bytes() -> int | None:
    """The limit on a render's fragment bytes: ``$UNICORN_MAX_RENDER_BYTES``, else 16 GiB (None: no limit).

    Raises:
        unicorn.checks.EnvironmentLimitError: the variable is not a number >= 0.
    """
    return env_limit(MAX_RENDER_BYTES_ENV, DEFAULT_MAX_RENDER_BYTES, "bytes")


def check_render_size(
    batch_size: int, image_size: tuple[int, int], faces_per_pixel: int, max_bytes: int | None = None
) -> None:
    """Refuse a render whose fragments could exceed the limit, before anything is allocated.

    The bound is ``B x H x W x K x PAIR_BYTES``: the packed pairs if every pixel of the raster (supersampled
    when the rasterizer is) kept K faces. Actual renders usually keep fewer pairs (a mesh covers part of the
    image, and the layered renderer drops what an opaque face hides), but the bound is what a frame-filling
    mesh can reach.

    Args:
        batch_size: B.
        image_size: (H, W) of the raster.
        faces_per_pixel: K.
        max_bytes: the limit; None: :func:`max_render_bytes`; 0: no limit.

    Raises:
        RenderSizeError: over the limit (naming ``image_size``, the estimate and how to raise the limit).
    """
    limit = max_render_bytes() if max_bytes is None else (max_bytes or None)
    H, W = image_size
    need = batch_size * H * W * faces_per_pixel * PAIR_BYTES
    if limit is not None and need > limit:
        raise RenderSizeError(
            f"image_size: {batch_size} x {H}x{W} pixels (supersampled where the renderer is) with "
            f"faces_per_pixel={faces_per_pixel} may need {need / 2**30:.3g} GiB of fragments (B x H x W x K x "
            f"{PAIR_BYTES} bytes), over the limit of {limit / 2**30:.3g} GiB; render smaller or raise the limit "
            f"(the renderer's max_bytes, or {MAX_RENDER_BYTES_ENV}; 0: none)"
        )


def _check_candidates(count: int, limit: int, blurred: bool) -> None:
    """Refuse a render whose candidate pairs of one image (each face against the pixels of its bounding box, grown
    by the blur radius) could take more than ``limit`` bytes while they are ranked."""
    need = count * CANDIDATE_BYTES
    if need > limit:
        cause = (
            "the faces' bounding boxes, grown by the blur radius (sigma)," if blurred else "the faces' bounding boxes"
        )
        fix = "a smaller sigma or image" if blurred else "a smaller image or smaller faces (long thin ones cost most)"
        raise RenderSizeError(
            f"{cause} cover {count:,} candidate face-pixel pairs in one image, which may need {need / 2**30:.3g} GiB "
            f"({CANDIDATE_BYTES} bytes each), over the limit of {limit / 2**30:.3g} GiB; use {fix}, or raise the "
            f"limit (the renderer's max_bytes, or {MAX_RENDER_BYTES_ENV}; 0: none)"
        )


def check_sigma(sigma: float) -> None:
    """Raise RenderError unless the occupancy temperature ``sigma`` is a finite number >= 0."""
    if not (is_real(sigma) and 0 <= sigma < math.inf):
        raise RenderError(f"sigma must be finite and >= 0, got {sigma!r}")


def blur_radius_from_sigma(sigma: float, eps: float = 1e-4) -> float:
    """Squared NDC radius beyond which a face's occupancy falls below ``eps``: ``ln(1 / eps - 1) * sigma``.

    For the layered occupancy ``exp(-d / sigma)`` and SoftRas' ``sigmoid(-d / sigma)`` alike this is where the
    face stops mattering (1e-4 by default, as in the reference).
    """
    check_sigma(sigma)
    if not 0 < eps < 0.5:
        raise RenderError(f"eps must be in (0, 0.5), the occupancy below which a face stops mattering, got {eps}")
    return math.log(1.0 / eps - 1.0) * sigma


def check_pose_inputs(R: torch.Tensor | None, T: torch.Tensor | None, batch_size: int) -> None:
    """Validate a world-to-view pose: R (B, 3, 3) and T (B, 3), floating point, finite and on one device, or both
    None (the finiteness is one host read, skipped inside :func:`unicorn.hostsync.sync_free`)."""
    if (R is None) != (T is None):
        raise ValueError("give both R and T, or neither (verts already in view coordinates)")
    if R is None or T is None:
        return
    check_rotations(R, "R", batch_size)  # an integer R would be cast and render a wrong pose
    check_translations(T, "T", batch_size)
    if R.device != T.device:  # read together below
        raise ValueError(f"R is on {R.device} but T is on {T.device}")
    if is_sync_free():
        return
    finite = torch.stack([torch.isfinite(R).all(), torch.isfinite(T).all()]).tolist()  # one device sync
    for name, ok in zip("RT", finite):
        if not ok:
            raise NonFiniteValueError(f"{name} contains NaN or infinite values")


def check_mesh_inputs(
    verts: torch.Tensor, faces: torch.Tensor, finite_also: Mapping[str, torch.Tensor] | None = None
) -> None:
    """Validate a batch of meshes with shared topology: verts (B, V, 3) float, faces (F, 3) integer in [0, V),
    finite vertices; empty batches, meshes and face lists are allowed (:func:`unicorn.checks.check_mesh`).
    ``finite_also`` (a render's colours, by argument name) must be finite too, checked in the same host read."""
    check_mesh(verts, faces, allow_empty=True, finite=True, finite_also=finite_also)


def check_whole_number(name: str, value: Any, low: int) -> None:
    """Raise RenderError unless ``value`` is a whole number >= ``low`` (2.0 is 2; 2.5, NaN or True are errors)."""
    number = is_real(value) and math.isfinite(value)
    if not (number and float(value).is_integer() and value >= low):
        raise RenderError(f"{name} must be a whole number >= {low}, got {value!r}")


def rasterize_meshes(
    verts_ndc: torch.Tensor,
    faces: torch.Tensor,
    image_size: int | tuple[int, int],
    blur_radius: float = 0.0,
    faces_per_pixel: int = 1,
    truncate_opaque: bool = False,
    max_candidates: int = 1 << 23,
    check_inputs: bool = True,
    max_bytes: int | None = None,
    perspective_correct: bool = False,
    capacity: tuple[int, int] | None = None,
) -> Fragments:
    """Rasterize a batch of projected meshes into packed top-K fragments.

    A face is a candidate for a pixel if its projection contains the pixel centre (a centre on an edge shared by
    two faces belongs to one of them, ``Fragments.inside``), or if the squared NDC distance from the centre to the
    face is below ``blur_radius``. The ``faces_per_pixel`` nearest candidates by view depth are kept (depths
    compared in float32). Faces with a vertex at depth <= 1e-6 (on or behind the camera plane; faces are not
    clipped) and faces with a 2D area <= 1e-8 are skipped; back faces are kept.

    Args:
        verts_ndc: (B, V, 3) projected vertices ``(x_ndc, y_ndc, z_view)`` (see
            :meth:`unicorn.geometry.cameras.PerspectiveCamera.project`); gradients flow to them.
        faces: (F, 3) long vertex indices shared by the batch.
        image_size: H or (H, W).
        blur_radius: squared NDC radius for near-miss faces; 0 keeps only faces containing the pixel.
        faces_per_pixel: K, the largest number of faces kept per pixel.
        truncate_opaque: drop the faces behind the nearest face that contains the pixel, and keep that face
            (in the last slot, when more near misses lie in front of it than the others hold). Exact for
            compositing in which a containing face is opaque (the layered renderer), and much cheaper.
        max_candidates: stage-1 work budget; images are processed in chunks of at most this many candidate
            (pixel, face) pairs (a single image is never split).
        check_inputs: validate shapes, dtypes, index ranges and finiteness.
        max_bytes: refuse, before allocating, a render whose fragments could exceed this many bytes
            (:func:`check_render_size`); None: :func:`max_render_bytes`; 0: no limit.
        perspective_correct: barycentrics of the 3D point of the face seen at the pixel centre (PyTorch3D's
            ``perspective_correct``: ``(b_i / z_i) / sum_j (b_j / z_j)`` of the screen-space ``b`` and the corner
            depths ``z``) instead of the screen-space ones, then clipped likewise; depth, colours and UVs are
            interpolated with them, so the depth is the face's true depth at the pixel. False (the default, the
            UNICORN reference's): screen-space barycentrics, which interpolate affinely across the projected face.
        capacity: None (default), or ``(candidates, pairs)``: select in buffers of that fixed size without reading
            the device back (:mod:`unicorn.render.fixed`; ``max_candidates`` is then unused): the fragments hold
            ``pairs`` rows, the last transparent padding (``Fragments.valid``), and ``Fragments.sizes`` says on the
            device what the batch needed.

    Returns:
        :class:`~unicorn.render.fragments.Fragments`. A pixel with more than ``faces_per_pixel`` candidates keeps
        the nearest; ``Fragments.overflow`` counts such pixels, and the count goes to the active
        :class:`~unicorn.render.overflow.OverflowCounter`, or else to a warning
        (:class:`~unicorn.render.overflow.RenderOverflowWarning`) once per ``faces_per_pixel`` setting and process
        (:func:`~unicorn.render.overflow.note_overflow`; not for a ``capacity`` render inside
        :func:`unicorn.hostsync.sync_free`, whose count stays on the device).
    """
    if check_inputs:
        check_mesh_inputs(verts_ndc, faces)
    check_whole_number("faces_per_pixel", faces_per_pixel, 1)
    check_whole_number("max_candidates", max_candidates, 1)
    faces_per_pixel, max_candidates = int(faces_per_pixel), int(max_candidates)  # 2.0 is accepted, as 2
    if max_bytes is not None:
        check_whole_number("max_bytes", max_bytes, 0)
    for name, flag in (("truncate_opaque", truncate_opaque), ("perspective_correct", perspective_correct)):
        if not isinstance(flag, bool):
            raise RenderError(f"{name} must be True or False, got {flag!r}")
    check_blur_radius(blur_radius)
    H, W = image_hw(image_size)
    B = verts_ndc.shape[0]
    check_render_size(B, (H, W), faces_per_pixel, max_bytes)
    faces = faces.long()
    if capacity is not None and B * faces.shape[0] * verts_ndc.shape[1] > 0:  # (nothing to draw: the sizes are known)
        return _rasterize_fixed(
            verts_ndc, faces, (H, W), blur_radius, faces_per_pixel, truncate_opaque, capacity, perspective_correct
        )
    limit = max_render_bytes() if max_bytes is None else (max_bytes or None)
    check = None if limit is None else functools.partial(_check_candidates, limit=limit, blurred=blur_radius > 0)
    kept = select_pairs(
        verts_ndc, faces, (H, W), blur_radius, faces_per_pixel, truncate_opaque, max_candidates, perspective_correct,
        check_candidates=check,
    )  # fmt: skip
    bary, dists, zbuf = _recompute(verts_ndc, faces, kept, (H, W), perspective_correct)
    # one host read for both counts (the packed layout's sizes are data-dependent: see unicorn.render.selection)
    slot = kept.slot
    overflow, num_slots = torch.stack([kept.overflow, slot.max() + 1 if slot.numel() else slot.new_zeros(())]).tolist()
    note_overflow(overflow, B * H * W, faces_per_pixel)
    return Fragments(
        pix=kept.pix, slot=slot, face=kept.face, inside=kept.inside, bary=bary, dists=dists, zbuf=zbuf,
        batch_size=B, image_size=(H, W), num_slots=num_slots, overflow=overflow, sizes=kept.sizes,
    )  # fmt: skip


def _rasterize_fixed(
    verts_ndc: torch.Tensor,
    faces: torch.Tensor,
    image_size: tuple[int, int],
    blur_radius: float,
    faces_per_pixel: int,
    truncate_opaque: bool,
    capacity: tuple[int, int],
    perspective_correct: bool,
) -> Fragments:
    """:func:`rasterize_meshes` in fixed buffers: no host read; the padding rows made transparent."""
    B = verts_ndc.shape[0]
    kept = select_fixed(
        verts_ndc, faces, image_size, blur_radius, faces_per_pixel, truncate_opaque, capacity, perspective_correct
    )
    bary, dists, zbuf = _recompute(verts_ndc, faces, kept, image_size, perspective_correct)
    # where, not a product: the padding's geometry gets no gradient
    dists, zbuf = (torch.where(kept.valid, t, torch.inf) for t in (dists, zbuf))
    note_overflow(kept.overflow, B * image_size[0] * image_size[1], faces_per_pixel)
    return Fragments(
        pix=kept.pix, slot=kept.slot, face=kept.face, inside=kept.inside, bary=bary, dists=dists, zbuf=zbuf,
        batch_size=B, image_size=image_size, num_slots=faces_per_pixel, overflow=kept.overflow, valid=kept.valid,
        sizes=kept.sizes,
    )  # fmt: skip


def _padding_triangle(like: torch.Tensor) -> torch.Tensor:
    """(3, 3) the triangle (x_ndc, y_ndc, z_view) of the padding rows of fixed buffers, (1, -1, 1), (-1, 1, 1),
    (-1, -1, 1): its barycentrics are finite, so no gradient and no NaN reaches the mesh. Made on ``like``'s device
    and dtype: a host constant would be copied to the device at every render, a copy the host waits for (and a host
    input keeps ``torch.compile`` from capturing the step in CUDA graphs)."""
    xy = torch.eye(3, 2, device=like.device, dtype=like.dtype) * 2 - 1
    return torch.cat([xy, torch.ones_like(xy[:, :1])], dim=1)


def _recompute(
    verts_ndc: torch.Tensor,
    faces: torch.Tensor,
    kept: Selection,
    image_size: tuple[int, int],
    perspective_correct: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stage 2, differentiable: clipped barycentrics (M, 3) (perspective-corrected before clipping when asked),
    signed squared NDC distances (M,) (negative inside) and depths (M,) of the kept pairs, recomputed from the
    vertices so that gradients reach them."""
    H, W = image_size
    px_to_ndc2 = (2.0 / min(H, W)) ** 2
    vert_idx = kept.image.unsqueeze(1) * verts_ndc.shape[1] + faces.index_select(0, kept.face)  # (M, 3)
    tri = verts_ndc.reshape(-1, 3).index_select(0, vert_idx.reshape(-1)).view(-1, 3, 3)  # (M, 3, 3)
    if kept.valid is not None:  # the padding of fixed buffers: a fixed triangle, finite whatever the mesh
        tri = torch.where(kept.valid.view(-1, 1, 1), tri, _padding_triangle(tri))
    tri_px = ndc_to_pixel(tri[..., :2], (H, W))
    centre_x = (kept.pix % W).to(tri.dtype)
    centre_y = torch.div(kept.pix, W, rounding_mode="floor").remainder(H).to(tri.dtype)
    bary_raw, d2 = barycentric_and_distance(tri_px, centre_x, centre_y)
    if perspective_correct:
        bary_raw = perspective_correct_barycentric(bary_raw, tri[..., 2])
    bary = clip_barycentric(bary_raw)
    d2 = d2 * px_to_ndc2
    dists = torch.where(kept.inside, -d2, d2)
    zbuf = (bary * tri[..., 2]).sum(-1)
    return bary, dists, zbuf
