"""Soft top-K mesh rasterization in pure PyTorch (CPU and CUDA).

Two stages, so that neither the memory nor the gradient path ever touches a (B, H, W, F) tensor:

1. Selection, without gradient. Every face enumerates the pixel centres of its 2D bounding box grown by the
   blur radius (``repeat_interleave`` over per-face box sizes); an exact test keeps the pixels the face contains
   or passes within the blur radius of; one sort on a (pixel, depth) key ranks the faces of each pixel and the
   nearest ``faces_per_pixel`` are kept. Cost: O(sum of box areas + P log P), chunked over images.
2. Recomputation, with gradient. For the kept pairs only, barycentrics, signed distances and depth are
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

import math
import os
import warnings
from collections.abc import Mapping

import torch

from ..checks import check_mesh, check_rotations, check_translations
from ..geometry.cameras import image_hw
from .fragments import Fragments

__all__ = [
    "DEFAULT_MAX_RENDER_BYTES",
    "MAX_RENDER_BYTES_ENV",
    "PAIR_BYTES",
    "blur_radius_from_sigma",
    "check_mesh_inputs",
    "check_pose_inputs",
    "check_render_size",
    "max_render_bytes",
    "rasterize_meshes",
]

# depth is quantised to this many bits inside the sort key; the pixel index takes the bits above
_DEPTH_BITS = 31
# faces whose 2D area (NDC units) is at most this are degenerate, as in PyTorch3D
_MIN_FACE_AREA = 1e-8
# vertices closer to the camera plane than this (view units) make their face skipped
_MIN_DEPTH = 1e-6
#: the faces_per_pixel settings whose overflow was already reported in this process (see rasterize_meshes)
_OVERFLOW_WARNED: set[int] = set()
#: bytes of one packed (pixel, face) pair, rounded up: four int64 indices, the inside flag, and barycentrics,
#: distance and depth in float32 (53 bytes); autograd and the aggregators keep a few times that while rendering
PAIR_BYTES = 64
#: the largest fragments a render may need, ``B x H x W x K x PAIR_BYTES``: 16 GiB (a batch of 192 training
#: images of 64 x 64 with K = 25 needs at most 1.3 GB; a single 10000 x 10000 render with K = 25, 160 GB)
DEFAULT_MAX_RENDER_BYTES = 16 << 30
#: environment variable holding that limit; 0 means no limit
MAX_RENDER_BYTES_ENV = "UNICORN_MAX_RENDER_BYTES"


def max_render_bytes() -> int | None:
    """The limit on a render's fragment bytes: ``$UNICORN_MAX_RENDER_BYTES``, else 16 GiB (None: no limit)."""
    text = os.environ.get(MAX_RENDER_BYTES_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_RENDER_BYTES
    try:
        value = int(float(text))
    except ValueError:
        raise ValueError(f"{MAX_RENDER_BYTES_ENV}={text!r} is not a number of bytes") from None
    return value if value > 0 else None


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
        ValueError: over the limit (naming ``image_size``, the estimate and how to raise the limit).
    """
    limit = max_render_bytes() if max_bytes is None else (max_bytes or None)
    H, W = image_size
    need = batch_size * H * W * faces_per_pixel * PAIR_BYTES
    if limit is not None and need > limit:
        raise ValueError(
            f"image_size: {batch_size} x {H}x{W} pixels (supersampled where the renderer is) with "
            f"faces_per_pixel={faces_per_pixel} may need {need / 2**30:.3g} GiB of fragments (B x H x W x K x "
            f"{PAIR_BYTES} bytes), over the limit of {limit / 2**30:.3g} GiB; render smaller or raise the limit "
            f"(the renderer's max_bytes, or {MAX_RENDER_BYTES_ENV}; 0: none)"
        )


def blur_radius_from_sigma(sigma: float, eps: float = 1e-4) -> float:
    """Squared NDC radius beyond which a face's occupancy falls below ``eps``: ``ln(1 / eps - 1) * sigma``.

    For the layered occupancy ``exp(-d / sigma)`` and SoftRas' ``sigmoid(-d / sigma)`` alike this is where the
    face stops mattering (1e-4 by default, as in the reference).
    """
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be finite and >= 0, got {sigma}")
    return math.log(1.0 / eps - 1.0) * sigma


def check_pose_inputs(R: torch.Tensor | None, T: torch.Tensor | None, batch_size: int) -> None:
    """Validate a world-to-view pose: R (B, 3, 3) and T (B, 3), floating point and finite, or both None."""
    if (R is None) != (T is None):
        raise ValueError("give both R and T, or neither (verts already in view coordinates)")
    if R is None or T is None:
        return
    check_rotations(R, "R", batch_size)  # an integer R would be cast and render a wrong pose
    check_translations(T, "T", batch_size)
    finite = torch.stack([torch.isfinite(R).all(), torch.isfinite(T).all()]).tolist()  # one device sync
    for name, ok in zip("RT", finite):
        if not ok:
            raise ValueError(f"{name} contains NaN or infinite values")


def check_mesh_inputs(
    verts: torch.Tensor, faces: torch.Tensor, finite_also: Mapping[str, torch.Tensor] | None = None
) -> None:
    """Validate a batch of meshes with shared topology: verts (B, V, 3) float, faces (F, 3) integer in [0, V),
    finite vertices; empty batches, meshes and face lists are allowed (:func:`unicorn.checks.check_mesh`).
    ``finite_also`` (a render's colours, by argument name) must be finite too, checked in the same host read."""
    check_mesh(verts, faces, allow_empty=True, finite=True, finite_also=finite_also)


def _face_boxes(
    fx: torch.Tensor, fy: torch.Tensor, radius_px: float, H: int, W: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Integer pixel-centre ranges [x0, x0 + w) x [y0, y0 + h) covered by each face box grown by the radius."""
    x0 = torch.ceil(fx.amin(-1) - radius_px).clamp(min=0)
    x1 = torch.floor(fx.amax(-1) + radius_px).clamp(max=W - 1)
    y0 = torch.ceil(fy.amin(-1) - radius_px).clamp(min=0)
    y1 = torch.floor(fy.amax(-1) + radius_px).clamp(max=H - 1)
    w = (x1 - x0 + 1).clamp(min=0).long()
    h = (y1 - y0 + 1).clamp(min=0).long()
    return x0.long(), y0.long(), w, h


def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def _barycentric(tri: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Unclipped screen-space barycentrics (N, 3) of points (px, py) in 2D triangles (N, 3, 2)."""
    x0, x1, x2 = tri[..., 0].unbind(-1)
    y0, y1, y2 = tri[..., 1].unbind(-1)
    area = _edge(x0, y0, x1, y1, x2, y2).unsqueeze(-1)
    w = torch.stack([_edge(x1, y1, x2, y2, px, py), _edge(x2, y2, x0, y0, px, py), _edge(x0, y0, x1, y1, px, py)], -1)
    return w / area


def _barycentric_coefficients(tri: torch.Tensor) -> torch.Tensor:
    """(N, 9) coefficients ``(a, b, c)`` of the affine maps ``w_i = a_i x + b_i y + c_i`` giving the unclipped
    barycentrics of a point (x, y) in the 2D triangles (N, 3, 2)."""
    x, y = tri[..., 0], tri[..., 1]
    xj, yj = x.roll(-1, dims=-1), y.roll(-1, dims=-1)  # vertex i's opposite edge runs from j = i+1 to k = i+2
    xk, yk = x.roll(-2, dims=-1), y.roll(-2, dims=-1)
    area = _edge(x[..., 0], y[..., 0], x[..., 1], y[..., 1], x[..., 2], y[..., 2]).unsqueeze(-1)
    a = -(yk - yj) / area
    b = (xk - xj) / area
    c = ((yk - yj) * xj - (xk - xj) * yj) / area
    return torch.cat([a, b, c], dim=-1)


def _segment_distance2(px, py, ax, ay, bx, by):
    """Squared distance from points to segments [a, b], the segment parameter clamped to [0, 1]."""
    ex, ey = bx - ax, by - ay
    dx, dy = px - ax, py - ay
    t = ((dx * ex + dy * ey) / (ex * ex + ey * ey).clamp_min(1e-20)).clamp(0.0, 1.0)
    return (dx - t * ex) ** 2 + (dy - t * ey) ** 2


def _boundary_distance2(tri: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Squared distance (N,) from points to the boundary of 2D triangles (N, 3, 2)."""
    x0, x1, x2 = tri[..., 0].unbind(-1)
    y0, y1, y2 = tri[..., 1].unbind(-1)
    d01 = _segment_distance2(px, py, x0, y0, x1, y1)
    d12 = _segment_distance2(px, py, x1, y1, x2, y2)
    d20 = _segment_distance2(px, py, x2, y2, x0, y0)
    return torch.minimum(torch.minimum(d01, d12), d20)


def _barycentric_and_distance(
    tri: torch.Tensor, px: torch.Tensor, py: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unclipped barycentrics (N, 3) and squared distance (N,) to the boundary of 2D triangles (N, 3, 2)."""
    return _barycentric(tri, px, py), _boundary_distance2(tri, px, py)


def _clip_barycentric(bary: torch.Tensor) -> torch.Tensor:
    clipped = bary.clamp_min(0.0)
    return clipped / clipped.sum(-1, keepdim=True).clamp_min(1e-5)


def _select_chunk(
    fpx: torch.Tensor,
    fz: torch.Tensor,
    counts: torch.Tensor,
    boxes: tuple[torch.Tensor, ...],
    first_image: int,
    H: int,
    W: int,
    px_to_ndc2: float,
    blur_radius: float,
    faces_per_pixel: int,
    truncate_opaque: bool,
) -> tuple[torch.Tensor, ...]:
    """Stage 1 for a chunk of images: kept (pixel, face) pairs ranked by depth. No gradient.

    Host syncs: the packed layout is what keeps memory at O(kept pairs) instead of O(B H W F), and its sizes
    are data-dependent, so this pass reads three sizes back from the device (the candidate count ``P`` and the
    two ``nonzero`` selections, plus one for the near-miss subset when ``blur_radius > 0``). Everything else
    stays on the device.
    """
    nb, F = counts.shape
    flat_counts = counts.reshape(-1)
    active = flat_counts.nonzero().squeeze(1)  # faces with at least one candidate pixel
    c = flat_counts.index_select(0, active)
    P = int(c.sum())
    empty = fpx.new_empty(0, dtype=torch.long)
    if P == 0:
        return empty, empty, empty, empty.bool(), empty.new_zeros(())
    dev = fpx.device
    # int32 candidate indices: half the memory traffic of int64 on the largest tensors of the pass
    owner = torch.repeat_interleave(torch.arange(active.numel(), device=dev, dtype=torch.int32), c, output_size=P)
    start = (torch.cumsum(c, 0) - c).int()
    local = torch.arange(P, device=dev, dtype=torch.int32) - start.index_select(0, owner)
    x0, y0, w, _ = (b.reshape(-1).index_select(0, active).int() for b in boxes)
    w_o = w.index_select(0, owner)
    px = x0.index_select(0, owner) + local % w_o
    py = y0.index_select(0, owner) + torch.div(local, w_o, rounding_mode="floor")
    del local, start

    flat_face = active.index_select(0, owner)  # index into (nb * F)
    # barycentrics are affine in the pixel position: three multiply-adds per candidate
    coef = _barycentric_coefficients(fpx.reshape(-1, 3, 2).index_select(0, active)).index_select(0, owner)
    del owner
    pxf, pyf = px.to(coef.dtype).unsqueeze(1), py.to(coef.dtype).unsqueeze(1)
    bary = torch.addcmul(torch.addcmul(coef[:, 6:], coef[:, :3], pxf), coef[:, 3:6], pyf)
    del coef
    inside = (bary > 0).all(-1)
    keep = inside.clone()
    if blur_radius > 0:
        # the distance test is only needed for the candidates outside their face
        out = (~inside).nonzero().squeeze(1)
        tri = fpx.reshape(-1, 6).index_select(0, flat_face.index_select(0, out)).view(-1, 3, 2)
        d2 = _boundary_distance2(tri, pxf.squeeze(1).index_select(0, out), pyf.squeeze(1).index_select(0, out))
        keep[out] = d2 * px_to_ndc2 < blur_radius
        del tri, d2
    idx = keep.nonzero().squeeze(1)
    if idx.numel() == 0:
        return empty, empty, empty, empty.bool(), empty.new_zeros(())
    flat_face, px, py, inside = (t.index_select(0, idx) for t in (flat_face, px, py, inside))
    z = (_clip_barycentric(bary.index_select(0, idx)) * fz.reshape(-1, 3).index_select(0, flat_face)).sum(-1)
    del bary

    image = torch.div(flat_face, F, rounding_mode="floor")
    pix_local = (image * H + py.long()) * W + px.long()
    zmin, zmax = z.min(), z.max()
    scale = (2**_DEPTH_BITS - 1) / (zmax - zmin).clamp_min(1e-12)
    zq = ((z - zmin) * scale).long().clamp_(0, 2**_DEPTH_BITS - 1)
    order = torch.sort((pix_local << _DEPTH_BITS) | zq, stable=True).indices
    pix_local, flat_face, inside = (t.index_select(0, order) for t in (pix_local, flat_face, inside))

    n = pix_local.numel()
    ar = torch.arange(n, device=dev)
    is_start = torch.ones(n, dtype=torch.bool, device=dev)
    is_start[1:] = pix_local[1:] != pix_local[:-1]
    seg_start = torch.cummax(torch.where(is_start, ar, torch.zeros_like(ar)), 0).values
    rank = ar - seg_start
    keep = torch.ones_like(is_start)
    if truncate_opaque:
        # everything behind the nearest face containing the pixel is fully hidden (alpha = 1 there)
        cum_inside = torch.cumsum(inside.long(), 0)
        inside_before = cum_inside - inside.long() - (cum_inside[seg_start] - inside[seg_start].long())
        keep = inside_before == 0
    overflow = (keep & (rank == faces_per_pixel)).sum()
    keep &= rank < faces_per_pixel
    sel = keep.nonzero().squeeze(1)
    pix = pix_local.index_select(0, sel) + first_image * H * W
    flat_face = flat_face.index_select(0, sel)
    face_global = flat_face % F
    image_global = torch.div(flat_face, F, rounding_mode="floor") + first_image
    return (
        pix,
        rank.index_select(0, sel),
        torch.stack([face_global, image_global]),
        inside.index_select(0, sel),
        overflow,
    )


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
) -> Fragments:
    """Rasterize a batch of projected meshes into packed top-K fragments.

    A face is a candidate for a pixel if its projection contains the pixel centre, or if the squared NDC
    distance from the centre to the face is below ``blur_radius``. The ``faces_per_pixel`` nearest candidates
    by view depth are kept. Faces with a vertex at depth <= 0 (behind the camera) and faces with a 2D area
    <= 1e-8 are skipped; back faces are kept.

    Args:
        verts_ndc: (B, V, 3) projected vertices ``(x_ndc, y_ndc, z_view)`` (see
            :meth:`unicorn.geometry.cameras.PerspectiveCamera.project`); gradients flow to them.
        faces: (F, 3) long vertex indices shared by the batch.
        image_size: H or (H, W).
        blur_radius: squared NDC radius for near-miss faces; 0 keeps only faces containing the pixel.
        faces_per_pixel: K, the largest number of faces kept per pixel.
        truncate_opaque: drop the faces behind the nearest face that contains the pixel. Exact for
            compositing in which a containing face is opaque (the layered renderer), and much cheaper.
        max_candidates: stage-1 work budget; images are processed in chunks of at most this many candidate
            (pixel, face) pairs (a single image is never split).
        check_inputs: validate shapes, dtypes, index ranges and finiteness.
        max_bytes: refuse, before allocating, a render whose fragments could exceed this many bytes
            (:func:`check_render_size`); None: :func:`max_render_bytes`; 0: no limit.

    Returns:
        :class:`~unicorn.render.fragments.Fragments`.
    """
    if check_inputs:
        check_mesh_inputs(verts_ndc, faces)
    if faces_per_pixel < 1:
        raise ValueError(f"faces_per_pixel must be >= 1, got {faces_per_pixel}")
    if not (math.isfinite(blur_radius) and blur_radius >= 0):
        raise ValueError(f"blur_radius must be finite and >= 0, got {blur_radius}")
    H, W = image_hw(image_size)
    B, V, _ = verts_ndc.shape
    check_render_size(B, (H, W), faces_per_pixel, max_bytes)
    S = min(H, W)
    faces = faces.long()
    F = faces.shape[0]
    px_to_ndc2 = (2.0 / S) ** 2
    radius_px = math.sqrt(blur_radius) * S / 2.0

    def to_pixels(v: torch.Tensor) -> torch.Tensor:
        return torch.stack([(W - 1 - v[..., 0] * S) / 2, (H - 1 - v[..., 1] * S) / 2], dim=-1)

    dev = verts_ndc.device
    pieces: list[tuple[torch.Tensor, ...]] = []
    overflow = torch.zeros((), dtype=torch.long, device=verts_ndc.device)
    if B > 0 and F > 0 and V > 0:
        with torch.no_grad():
            v = verts_ndc.detach()
            corners = v.index_select(1, faces.reshape(-1)).view(B, F, 3, 3)
            fpx = to_pixels(corners)  # (B, F, 3, 2)
            fz = corners[..., 2].contiguous()  # (B, F, 3); contiguous for fast row gathers
            e1 = fpx[:, :, 1] - fpx[:, :, 0]
            e2 = fpx[:, :, 2] - fpx[:, :, 0]
            area_ndc = 0.5 * (e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]) * px_to_ndc2
            valid = (fz.amin(-1) > _MIN_DEPTH) & (area_ndc.abs() > _MIN_FACE_AREA)
            boxes = _face_boxes(fpx[..., 0], fpx[..., 1], radius_px, H, W)
            counts = boxes[2] * boxes[3] * valid
            per_image = counts.sum(1).tolist()  # one host read: chunks are planned from the per-image work
            start = 0
            while start < B:
                stop, total = start + 1, per_image[start]
                while stop < B and total + per_image[stop] <= max_candidates:
                    total += per_image[stop]
                    stop += 1
                sl = slice(start, stop)
                *piece, n_over = _select_chunk(
                    fpx[sl], fz[sl], counts[sl], tuple(b[sl] for b in boxes), start, H, W,
                    px_to_ndc2, blur_radius, faces_per_pixel, truncate_opaque,
                )  # fmt: skip
                overflow += n_over
                if piece[0].numel():
                    pieces.append(tuple(piece))
                start = stop

    if pieces:
        pix = torch.cat([p[0] for p in pieces])
        slot = torch.cat([p[1] for p in pieces])
        face, image = torch.cat([p[2] for p in pieces], dim=1)
        inside = torch.cat([p[3] for p in pieces])
    else:
        pix = slot = face = image = torch.zeros(0, dtype=torch.long, device=dev)
        inside = torch.zeros(0, dtype=torch.bool, device=dev)

    # stage 2: differentiable recomputation for the kept pairs
    vert_idx = image.unsqueeze(1) * V + faces.index_select(0, face)  # (M, 3)
    tri = verts_ndc.reshape(-1, 3).index_select(0, vert_idx.reshape(-1)).view(-1, 3, 3)  # (M, 3, 3)
    tri_px = to_pixels(tri)
    centre_x = (pix % W).to(tri.dtype)
    centre_y = torch.div(pix, W, rounding_mode="floor").remainder(H).to(tri.dtype)
    bary_raw, d2 = _barycentric_and_distance(tri_px, centre_x, centre_y)
    bary = _clip_barycentric(bary_raw)
    d2 = d2 * px_to_ndc2
    dists = torch.where(inside, -d2, d2)
    zbuf = (bary * tri[..., 2]).sum(-1)

    # one host read for both counts (the packed layout's sizes are data-dependent: see _select_chunk)
    overflow, num_slots = torch.stack([overflow, slot.max() + 1 if slot.numel() else slot.new_zeros(())]).tolist()
    if overflow and faces_per_pixel not in _OVERFLOW_WARNED:
        # once per setting and process: Python's own once-per-location registry is reset whenever any library
        # changes the warning filters (Lightning does, every step), which repeated this line thousands of times
        # in a training log; Fragments.overflow has the count of every call
        _OVERFLOW_WARNED.add(faces_per_pixel)
        warnings.warn(
            f"some pixels had more than faces_per_pixel={faces_per_pixel} candidate faces and the farthest were "
            "dropped (Fragments.overflow counts them; raise faces_per_pixel if it matters)",
            stacklevel=2,
        )
    return Fragments(
        pix=pix, slot=slot, face=face, inside=inside, bary=bary, dists=dists, zbuf=zbuf,
        batch_size=B, image_size=(H, W), num_slots=num_slots, overflow=overflow,
    )  # fmt: skip
