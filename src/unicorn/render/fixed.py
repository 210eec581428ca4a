"""Stage 1 of the rasterizer without host reads: the same kept pairs in buffers of a fixed capacity.

:func:`select_fixed` makes the selection of :func:`~unicorn.render.selection.select_pairs` with every size known in
advance: at most ``capacity = (candidates, pairs)`` (pixel, face) candidates are enumerated (each one's face found by
a search in the faces' running candidate counts instead of ``repeat_interleave`` over the drawable faces), every one
is tested and sorted (those not kept with keys past every pixel), and the kept pairs are gathered with
``nonzero_static`` into ``pairs`` rows. The rows past the kept ones are padding at the last pixel, in an extra slot,
marked by ``valid``; the rasterizer makes them transparent. Nothing is read back: the
sizes (candidates and kept pairs, the capacity needed) stay on the device, in :attr:`Selection.sizes`.

Where the capacity suffices, the kept pairs are those of :func:`~unicorn.render.selection.select_pairs` in the same
order, however it chunks the batch (``max_candidates``). Candidates and pairs beyond the capacity are dropped (the
farthest pairs of the last pixels).
"""

from __future__ import annotations

import math

import torch

from .selection import _DEPTH_BITS, Selection, _face_boxes, _project_faces, _slots, depth_key
from .triangles import (
    barycentric_coefficients,
    boundary_distance2,
    clip_barycentric,
    covered_barycentric,
    perspective_correct_barycentric,
)

__all__ = ["select_fixed"]


@torch.no_grad()
def select_fixed(
    verts_ndc: torch.Tensor,
    faces: torch.Tensor,
    image_size: tuple[int, int],
    blur_radius: float,
    faces_per_pixel: int,
    truncate_opaque: bool,
    capacity: tuple[int, int],
    perspective_correct: bool = False,
) -> Selection:
    """:func:`~unicorn.render.selection.select_pairs` in fixed buffers: ``capacity[1]`` pairs, the last padding
    (``Selection.valid``), from at most ``capacity[0]`` candidates; ``Selection.sizes`` (2,) the candidates and pairs
    the batch needed (on the device)."""
    H, W = image_size
    B, F = verts_ndc.shape[0], faces.shape[0]
    n_cand, n_pairs = (max(int(c), 1) for c in capacity)
    flat_face, px, py, inside, keep, z, total = _candidates(
        verts_ndc.detach(), faces, image_size, blur_radius, n_cand, perspective_correct
    )
    image = torch.div(flat_face, F, rounding_mode="floor")
    pix = (image * H + py.long()) * W + px.long()
    # the candidates not kept sort last, each at its own pixel past the batch's (rank 0: never an overflow)
    p = torch.arange(n_cand, device=pix.device)
    pix = torch.where(keep, pix, B * H * W + p)
    order = _depth_key(pix, z, keep).sort(stable=True).indices
    pix, flat_face, inside, keep = (t.index_select(0, order) for t in (pix, flat_face, inside, keep))
    rank, kept, overflow = _slots(pix, inside, faces_per_pixel, truncate_opaque)
    kept &= keep
    n_kept = kept.sum()
    # padding: row 0 of the candidates at the last pixel, in slot faces_per_pixel (the rasterizer makes it
    # transparent and draws it from a fixed triangle)
    sel = torch.nonzero_static(kept, size=n_pairs, fill_value=0).squeeze(1)
    valid = torch.arange(n_pairs, device=sel.device) < n_kept
    flat_face = flat_face.index_select(0, sel)
    return Selection(
        pix=torch.where(valid, pix.index_select(0, sel), max(B * H * W - 1, 0)),
        slot=torch.where(valid, rank.index_select(0, sel), faces_per_pixel),
        face=flat_face % max(F, 1),
        image=torch.div(flat_face, max(F, 1), rounding_mode="floor"),
        inside=inside.index_select(0, sel) & valid,
        overflow=overflow,
        valid=valid,
        sizes=torch.stack([total, n_kept]),
    )


def _candidates(
    verts_ndc: torch.Tensor,
    faces: torch.Tensor,
    image_size: tuple[int, int],
    blur_radius: float,
    n_cand: int,
    perspective_correct: bool,
) -> tuple[torch.Tensor, ...]:
    """The first ``n_cand`` (pixel, face) candidates of the batch, in ``_candidate_pixels``' order: ``(flat_face,
    px, py, inside, keep, z, total)``, each (n_cand,) but ``total``, the 0-dim count of candidates; ``keep`` is
    False past it."""
    H, W = image_size
    S = min(H, W)
    px_to_ndc2 = (2.0 / S) ** 2
    fpx, fz, drawable = _project_faces(verts_ndc, faces, (H, W), px_to_ndc2)
    boxes = _face_boxes(fpx[..., 0], fpx[..., 1], math.sqrt(blur_radius) * S / 2.0, H, W)
    counts = (boxes[2] * boxes[3] * drawable).reshape(-1)  # (B F,) candidates of each face
    ends = torch.cumsum(counts, 0)
    total = ends[-1]
    p = torch.arange(n_cand, device=fpx.device)
    # the face of candidate p: the first whose running count passes p (faces without candidates are skipped)
    flat_face = torch.searchsorted(ends, p, right=True).clamp_(max=counts.numel() - 1)
    local = (p - (ends - counts).index_select(0, flat_face)).int()
    px, py, bary, inside = _candidate_coordinates(fpx, flat_face, local, boxes)
    keep = _coverage_all(fpx, flat_face, px, py, inside, px_to_ndc2, blur_radius)
    keep &= p < total
    z = _depth(bary, fz.reshape(-1, 3).index_select(0, flat_face), perspective_correct)
    return flat_face, px, py, inside, keep, z, total


def _candidate_coordinates(
    fpx: torch.Tensor, face: torch.Tensor, local: torch.Tensor, boxes: tuple[torch.Tensor, ...]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Column and row (P,) int32 of candidate ``local`` (P,) int32 in the box of its face ``face`` (P,) (a flat
    index over (B F)), its unclipped barycentrics (P, 3) and whether the face covers it (P,): the values of
    ``_candidate_pixels``."""
    x0, y0, w, _ = (b.reshape(-1).index_select(0, face).int() for b in boxes)
    w = w.clamp_(min=1)  # the candidates past the count may sit on faces without any
    px = x0 + local % w
    py = y0 + torch.div(local, w, rounding_mode="floor")
    coef = barycentric_coefficients(fpx.reshape(-1, 3, 2))
    bary, inside = covered_barycentric(coef, face, px.to(coef.dtype).unsqueeze(1), py.to(coef.dtype).unsqueeze(1))
    return px, py, bary, inside


def _coverage_all(
    fpx: torch.Tensor,
    face: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    inside: torch.Tensor,
    px_to_ndc2: float,
    blur_radius: float,
) -> torch.Tensor:
    """Which candidates to keep (P,): those their face covers, or within the blur radius of it (the distance test
    on every one)."""
    if blur_radius <= 0:
        return inside.clone()
    tri = fpx.reshape(-1, 6).index_select(0, face).view(-1, 3, 2)
    d2 = boundary_distance2(tri, px.to(fpx.dtype), py.to(fpx.dtype))
    return inside | (d2 * px_to_ndc2 < blur_radius)


def _depth_key(pix: torch.Tensor, z: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """``_depth_order``'s sort key (:func:`~unicorn.render.selection.depth_key`; 0 for the candidates not kept,
    whose depth may be anything)."""
    return (pix << _DEPTH_BITS) | torch.where(keep, depth_key(torch.where(keep, z, 1.0)), 0)


def _depth(bary: torch.Tensor, corner_z: torch.Tensor, perspective_correct: bool) -> torch.Tensor:
    """Depth (P,) at each candidate, interpolated with the clipped (perspective-corrected) barycentrics."""
    if perspective_correct:
        bary = perspective_correct_barycentric(bary, corner_z)
    return (clip_barycentric(bary) * corner_z).sum(-1)
