"""Stage 1 of the rasterizer: which faces each pixel keeps, ranked by depth (no gradient).

Every face enumerates the pixel centres of its 2D bounding box grown by the blur radius
(:func:`_candidate_pixels`); an exact test keeps the pixels the face contains or passes within the blur radius of
(:func:`_coverage`); one sort on a (pixel, depth) key ranks the faces of each pixel (:func:`_depth_order`) and
the nearest ``faces_per_pixel`` are kept (:func:`_slots`). Cost: O(sum of box areas + P log P), in chunks of
images of at most ``max_candidates`` (pixel, face) candidates (:func:`_chunks`).

Host syncs: the packed layout is what keeps memory at O(kept pairs) instead of O(B H W F), and its sizes are
data-dependent, so each chunk reads three sizes back from the device (the candidate count ``P`` and the two
``nonzero`` selections, plus one for the near-miss subset when ``blur_radius > 0``), and the plan of the chunks
one more. Everything else stays on the device.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import NamedTuple

import torch

from ..geometry.cameras import ndc_to_pixel
from .triangles import (
    barycentric_coefficients,
    boundary_distance2,
    clip_barycentric,
    covered_barycentric,
    perspective_correct_barycentric,
)

__all__ = ["Selection", "select_pairs"]

# the depth's bits in the sort key (:func:`depth_key`); the pixel index takes the bits above
_DEPTH_BITS = 31
# faces whose 2D area (NDC units) is at most this are degenerate, as in PyTorch3D
_MIN_FACE_AREA = 1e-8
# vertices closer to the camera plane than this (view units) make their face skipped
_MIN_DEPTH = 1e-6


class Selection(NamedTuple):
    """The kept (pixel, face) pairs, M of them, in (image, pixel, depth) order.

    ``pix`` (M,) flat pixel index over (B, H, W); ``slot`` (M,) the pair's depth rank at its pixel; ``face`` (M,)
    and ``image`` (M,) the face and the image; ``inside`` (M,) bool, the face contains the pixel centre;
    ``overflow`` a 0-dim count of the pixels that had more than ``faces_per_pixel`` candidates. The selection in
    fixed buffers (:func:`unicorn.render.fixed.select_fixed`) adds ``valid`` (M,) bool, False on its padding rows,
    and ``sizes`` (2,) the candidates and pairs the batch needed.
    """

    pix: torch.Tensor
    slot: torch.Tensor
    face: torch.Tensor
    image: torch.Tensor
    inside: torch.Tensor
    overflow: torch.Tensor
    valid: torch.Tensor | None = None
    sizes: torch.Tensor | None = None


@torch.no_grad()
def select_pairs(
    verts_ndc: torch.Tensor,
    faces: torch.Tensor,
    image_size: tuple[int, int],
    blur_radius: float,
    faces_per_pixel: int,
    truncate_opaque: bool,
    max_candidates: int,
    perspective_correct: bool = False,
    check_candidates: Callable[[int], None] | None = None,
) -> Selection:
    """The nearest ``faces_per_pixel`` faces of every pixel (see :func:`~unicorn.render.raster.rasterize_meshes`).

    Args:
        verts_ndc: (B, V, 3) projected vertices ``(x_ndc, y_ndc, z_view)``.
        faces: (F, 3) long vertex indices.
        image_size: (H, W).
        blur_radius: squared NDC radius for near-miss faces.
        faces_per_pixel: K >= 1.
        truncate_opaque: drop the faces behind the nearest face that contains the pixel, and keep that face (in
            the last slot when more near misses lie in front of it).
        max_candidates: the most candidate pairs of a chunk of images (a single image is never split).
        perspective_correct: rank the faces by the depth read with perspective-correct barycentrics (the true
            depth of the face at the pixel) instead of the screen-space ones.
        check_candidates: called with the most candidate pairs of one image before any is made (it raises to
            refuse a render whose blur radius would make too many).
    """
    H, W = image_size
    B, V, _ = verts_ndc.shape
    F = faces.shape[0]
    dev = verts_ndc.device
    overflow = torch.zeros((), dtype=torch.long, device=dev)
    n_candidates = 0
    pieces: list[tuple[torch.Tensor, ...]] = []
    if B > 0 and F > 0 and V > 0:
        S = min(H, W)
        px_to_ndc2 = (2.0 / S) ** 2
        fpx, fz, valid = _project_faces(verts_ndc.detach(), faces, (H, W), px_to_ndc2)
        boxes = _face_boxes(fpx[..., 0], fpx[..., 1], math.sqrt(blur_radius) * S / 2.0, H, W)
        counts = boxes[2] * boxes[3] * valid
        per_image = counts.sum(1).tolist()  # one host read: the per-image work
        n_candidates = sum(per_image)
        if check_candidates is not None:
            check_candidates(max(per_image))
        for sl in _chunks(per_image, max_candidates):
            *piece, n_over = _select_chunk(
                fpx[sl], fz[sl], counts[sl], tuple(b[sl] for b in boxes), sl.start, (H, W),
                px_to_ndc2, blur_radius, faces_per_pixel, truncate_opaque, perspective_correct,
            )  # fmt: skip
            overflow += n_over
            if piece[0].numel():
                pieces.append(tuple(piece))
    if not pieces:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return Selection(empty, empty, empty, empty, empty.bool(), overflow, sizes=torch.tensor([n_candidates, 0]))
    pix, slot, face_image, inside = (torch.cat(parts, dim=-1) for parts in zip(*pieces))
    sizes = torch.tensor([n_candidates, pix.numel()])  # on the host: what select_fixed's buffers need
    return Selection(pix, slot, face_image[0], face_image[1], inside, overflow, sizes=sizes)


def _project_faces(
    verts_ndc: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int], px_to_ndc2: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Corners of every face in pixels (B, F, 3, 2), their depths (B, F, 3), and which faces can be drawn (B, F):
    in front of the camera and not degenerate."""
    B, F = verts_ndc.shape[0], faces.shape[0]
    corners = verts_ndc.index_select(1, faces.reshape(-1)).view(B, F, 3, 3)
    fpx = ndc_to_pixel(corners[..., :2], image_size)  # (B, F, 3, 2)
    fz = corners[..., 2].contiguous()  # contiguous for fast row gathers
    e1 = fpx[:, :, 1] - fpx[:, :, 0]
    e2 = fpx[:, :, 2] - fpx[:, :, 0]
    area_ndc = 0.5 * (e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]) * px_to_ndc2
    valid = (fz.amin(-1) > _MIN_DEPTH) & (area_ndc.abs() > _MIN_FACE_AREA)
    return fpx, fz, valid


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


def _chunks(per_image: list[int], max_candidates: int) -> Iterator[slice]:
    """Consecutive runs of images whose candidates sum to at most ``max_candidates`` (or a single image)."""
    start, B = 0, len(per_image)
    while start < B:
        stop, total = start + 1, per_image[start]
        while stop < B and total + per_image[stop] <= max_candidates:
            total += per_image[stop]
            stop += 1
        yield slice(start, stop)
        start = stop


def _select_chunk(
    fpx: torch.Tensor,
    fz: torch.Tensor,
    counts: torch.Tensor,
    boxes: tuple[torch.Tensor, ...],
    first_image: int,
    image_size: tuple[int, int],
    px_to_ndc2: float,
    blur_radius: float,
    faces_per_pixel: int,
    truncate_opaque: bool,
    perspective_correct: bool,
) -> tuple[torch.Tensor, ...]:
    """Stage 1 for a chunk of images: ``(pix, slot, (face, image) stacked, inside, overflow)``, pixels and images
    numbered in the whole batch."""
    H, W = image_size
    F = counts.shape[1]
    empty = fpx.new_empty(0, dtype=torch.long)
    nothing = empty, empty, empty, empty.bool(), empty.new_zeros(())
    candidates = _candidate_pixels(fpx, counts, boxes)
    if candidates is None:
        return nothing
    flat_face, px, py, bary, inside = candidates
    del candidates
    keep = _coverage(fpx, flat_face, px, py, inside, px_to_ndc2, blur_radius)
    idx = keep.nonzero().squeeze(1)
    if idx.numel() == 0:
        return nothing
    flat_face, px, py, inside, bary = (t.index_select(0, idx) for t in (flat_face, px, py, inside, bary))
    corner_z = fz.reshape(-1, 3).index_select(0, flat_face)
    if perspective_correct:
        bary = perspective_correct_barycentric(bary, corner_z)
    z = (clip_barycentric(bary) * corner_z).sum(-1)
    del bary, corner_z

    image = torch.div(flat_face, F, rounding_mode="floor")
    pix_local = (image * H + py.long()) * W + px.long()
    order = _depth_order(pix_local, z)
    pix_local, flat_face, inside = (t.index_select(0, order) for t in (pix_local, flat_face, inside))
    rank, keep, overflow = _slots(pix_local, inside, faces_per_pixel, truncate_opaque)
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


def _candidate_pixels(
    fpx: torch.Tensor, counts: torch.Tensor, boxes: tuple[torch.Tensor, ...]
) -> tuple[torch.Tensor, ...] | None:
    """Every pixel centre in every drawable face's box: ``(flat_face, px, py, bary, inside)`` per candidate, the
    face as an index into (nb * F), the pixel's column and row (int32), its unclipped barycentrics (P, 3) and
    whether the face covers it (:func:`~unicorn.render.triangles.covered_barycentric`); None when there is no
    candidate."""
    flat_counts = counts.reshape(-1)
    active = flat_counts.nonzero().squeeze(1)  # faces with at least one candidate pixel
    c = flat_counts.index_select(0, active)
    P = int(c.sum())
    if P == 0:
        return None
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

    flat_face = active.index_select(0, owner)
    # barycentrics are affine in the pixel position: two products per edge and candidate
    coef = barycentric_coefficients(fpx.reshape(-1, 3, 2).index_select(0, active))
    bary, inside = covered_barycentric(coef, owner, px.to(coef.dtype).unsqueeze(1), py.to(coef.dtype).unsqueeze(1))
    del owner
    return flat_face, px, py, bary, inside


def _coverage(
    fpx: torch.Tensor,
    flat_face: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    inside: torch.Tensor,
    px_to_ndc2: float,
    blur_radius: float,
) -> torch.Tensor:
    """Which candidates to keep (P,): those their face covers (``inside``), or within the blur radius of it."""
    keep = inside.clone()
    if blur_radius > 0:
        # the distance test is only needed for the candidates outside their face
        out = (~inside).nonzero().squeeze(1)
        tri = fpx.reshape(-1, 6).index_select(0, flat_face.index_select(0, out)).view(-1, 3, 2)
        d2 = boundary_distance2(tri, px.index_select(0, out).to(fpx.dtype), py.index_select(0, out).to(fpx.dtype))
        keep[out] = d2 * px_to_ndc2 < blur_radius
    return keep


def depth_key(z: torch.Tensor) -> torch.Tensor:
    """Depths (> 0) as int64 keys below ``2 ** _DEPTH_BITS`` in the order of the depths: the bits of ``z`` as float32
    read as an integer (a positive float's bits grow with it). Two faces are told apart wherever their depths differ
    in float32, whatever the depths of the other faces and images."""
    return z.float().view(torch.int32).long()


def _depth_order(pix: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """The permutation sorting the pairs by pixel, then by depth (:func:`depth_key`; ties keep their order)."""
    return torch.sort((pix << _DEPTH_BITS) | depth_key(z), stable=True).indices


def _slots(
    pix: torch.Tensor, inside: torch.Tensor, faces_per_pixel: int, truncate_opaque: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Of pairs sorted by pixel then depth: each pair's slot at its pixel (M,), which to keep (M,) and the count of
    pixels that overflowed ``faces_per_pixel`` (0-dim).

    With ``truncate_opaque``, a pixel's nearest containing face is always kept: when more than
    ``faces_per_pixel - 1`` near misses lie in front of it, the farthest of them give way and it takes the last
    slot (dropping it instead would leave a hole where the surface is opaque)."""
    n = pix.numel()
    dev = pix.device
    ar = torch.arange(n, device=dev)
    is_start = torch.ones(n, dtype=torch.bool, device=dev)
    is_start[1:] = pix[1:] != pix[:-1]
    seg_start = torch.cummax(torch.where(is_start, ar, torch.zeros_like(ar)), 0).values
    rank = ar - seg_start
    if not truncate_opaque:
        overflow = (rank == faces_per_pixel).sum()
        return rank, rank < faces_per_pixel, overflow
    # everything behind the nearest face containing the pixel is fully hidden (alpha = 1 there)
    cum_inside = torch.cumsum(inside.long(), 0)
    inside_before = cum_inside - inside.long() - (cum_inside[seg_start] - inside[seg_start].long())
    keep = inside_before == 0
    overflow = (keep & (rank == faces_per_pixel)).sum()
    late = keep & inside & (rank >= faces_per_pixel)  # an opaque face past the last slot
    # a scatter over the segment starts, not a nonzero: no read of the device
    late_at_pixel = torch.zeros(n, dtype=torch.long, device=dev).scatter_add_(0, seg_start, late.long())[seg_start]
    last = faces_per_pixel - 1
    keep &= ((rank < faces_per_pixel) & ~((late_at_pixel > 0) & (rank == last))) | late
    return torch.where(late, last, rank), keep, overflow
