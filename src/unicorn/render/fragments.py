"""The rasterizer's output: for every pixel, the nearest faces that cover it or pass within the blur radius.

Fragments are stored *packed*: one row per kept (pixel, face) pair, sorted by pixel and then by increasing
depth. Only pixels that some face reaches have rows, so memory grows with the covered area, not with
``B * H * W * faces_per_pixel``. :meth:`Fragments.to_dense` gives PyTorch3D's padded layout when needed.

Letters: B images, H x W pixels, F faces, M kept pairs, K slots per pixel (``num_slots``), R covered pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..checks import check_same_dtype, check_shape

__all__ = ["DenseFragments", "Fragments", "check_blend_inputs"]


@dataclass
class DenseFragments:
    """PyTorch3D-style padded fragments.

    Attributes:
        pix_to_face: (B, H, W, K) long, face index in [0, F) or -1 for an empty slot.
        zbuf: (B, H, W, K) view-space depth, -1 where empty.
        bary_coords: (B, H, W, K, 3) clipped barycentrics, -1 where empty.
        dists: (B, H, W, K) signed squared NDC distance (negative inside), -1 where empty.
    """

    pix_to_face: torch.Tensor
    zbuf: torch.Tensor
    bary_coords: torch.Tensor
    dists: torch.Tensor


@dataclass
class Fragments:
    """Packed fragments of a batch of meshes sharing one topology.

    Attributes:
        pix: (M,) long, flat pixel index ``b * H * W + row * W + col``; non-decreasing.
        slot: (M,) long, rank of the pair among the pixel's faces by increasing depth (0 = nearest).
        face: (M,) long, face index in [0, F).
        inside: (M,) bool, whether the projected face covers the pixel centre: inside it, or on an edge it owns
            (:func:`~unicorn.render.triangles.barycentric_coefficients`; of two faces sharing an edge, one).
        bary: (M, 3) barycentrics, clipped to >= 0 and renormalised (differentiable): screen-space, or those
            of the 3D point seen at the pixel when the rasterizer is ``perspective_correct``.
        dists: (M,) signed squared distance in NDC units from the pixel centre to the face boundary,
            negative inside (differentiable).
        zbuf: (M,) view-space depth at the pixel, interpolated with the clipped barycentrics (differentiable;
            with perspective-correct ones, the face's depth along the pixel's ray wherever the face contains it).
        batch_size: B.
        image_size: (H, W).
        num_slots: K, the largest number of pairs kept for one pixel (at most ``faces_per_pixel``).
        overflow: number of pixels that had more candidate faces than ``faces_per_pixel`` (the farthest
            were dropped); 0 means nothing was truncated. A 0-dim tensor on the device for the fragments in fixed
            buffers.
        valid: None, or (M,) bool for fragments in fixed buffers (the rasterizer without host reads,
            :mod:`unicorn.render.fixed`): False on the padding rows, which sit after the others at the last pixel,
            in slot ``num_slots`` (one past the last), and are transparent (``dists`` and ``zbuf`` infinite, not
            ``inside``). Every pixel is then a row of :meth:`rows`.
        sizes: (2,) long, the candidates and kept pairs the render needed (on the device for fixed buffers).
    """

    pix: torch.Tensor
    slot: torch.Tensor
    face: torch.Tensor
    inside: torch.Tensor
    bary: torch.Tensor
    dists: torch.Tensor
    zbuf: torch.Tensor
    batch_size: int
    image_size: tuple[int, int]
    num_slots: int
    overflow: int | torch.Tensor
    valid: torch.Tensor | None = None
    sizes: torch.Tensor | None = None

    @property
    def num_pairs(self) -> int:
        return int(self.pix.shape[0])

    @property
    def batch_index(self) -> torch.Tensor:
        """(M,) image index of every pair."""
        H, W = self.image_size
        return torch.div(self.pix, H * W, rounding_mode="floor")

    def rows(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Compact per-pixel layout: ``row`` (M,) in [0, R) for every pair and ``row_pix`` (R,) covered pixels."""
        if self.valid is not None:  # fixed buffers: every pixel is a row (no data-dependent size)
            H, W = self.image_size
            return self.pix, torch.arange(self.batch_size * H * W, device=self.pix.device)
        row_pix, row = torch.unique_consecutive(self.pix, return_inverse=True)
        return row, row_pix

    @property
    def slot_columns(self) -> int:
        """Slots of the per-pixel layouts: ``num_slots``, one more for the padding of fixed buffers (at least 1)."""
        return max(self.num_slots, 1) + (self.valid is not None)

    def to_dense(self, faces_per_pixel: int | None = None) -> DenseFragments:
        """Padded (B, H, W, K) tensors as PyTorch3D returns them (differentiable in bary, dists and zbuf).

        Args:
            faces_per_pixel: K, the rasterizer's ``faces_per_pixel`` for PyTorch3D's shapes, the slots past
                ``num_slots`` empty; None: K = ``num_slots``, the most faces any pixel kept (at least 1).

        Raises:
            ValueError: ``faces_per_pixel`` not a whole number (2.5, True), or below ``num_slots``.
        """
        from .raster import check_whole_number  # raster imports this module

        if faces_per_pixel is not None:
            check_whole_number("faces_per_pixel", faces_per_pixel, 1)
        k = max(self.num_slots, 1) if faces_per_pixel is None else int(faces_per_pixel)
        if k < max(self.num_slots, 1):
            raise ValueError(f"faces_per_pixel={faces_per_pixel} is below the {self.num_slots} faces a pixel kept")
        B, (H, W) = self.batch_size, self.image_size
        n, K = B * H * W, k + 1  # a column past the last for the padding rows of fixed buffers, left out below
        flat = (self.pix, self.slot if self.valid is None else torch.where(self.valid, self.slot, k))
        dev, dt = self.bary.device, self.bary.dtype
        pix_to_face = torch.full((n, K), -1, dtype=torch.long, device=dev).index_put(flat, self.face)
        zbuf = torch.full((n, K), -1.0, dtype=dt, device=dev).index_put(flat, self.zbuf)
        dists = torch.full((n, K), -1.0, dtype=dt, device=dev).index_put(flat, self.dists)
        bary = torch.full((n, K, 3), -1.0, dtype=dt, device=dev).index_put(flat, self.bary)
        return DenseFragments(
            pix_to_face=pix_to_face[:, :k].reshape(B, H, W, k),
            zbuf=zbuf[:, :k].reshape(B, H, W, k),
            bary_coords=bary[:, :k].reshape(B, H, W, k, 3),
            dists=dists[:, :k].reshape(B, H, W, k),
        )

    def first_layer(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest face containing each pixel: face ids (B, H, W) long (-1 where none) and depth (B, H, W)
        (0 where none; differentiable, as ``zbuf``). Near-miss faces (outside but within the blur radius) are
        ignored."""
        B, (H, W) = self.batch_size, self.image_size
        n = B * H * W
        dev = self.pix.device
        # the first *inside* pair of each pixel: pairs are depth-sorted within a pixel, so take the min slot
        sel = self.inside
        big = torch.iinfo(torch.long).max
        best = torch.full((n,), big, dtype=torch.long, device=dev)
        best = best.scatter_reduce(0, self.pix[sel], self.slot[sel], reduce="amin")
        hit = sel & (self.slot == best[self.pix])
        face_ids = torch.full((n,), -1, dtype=torch.long, device=dev)
        face_ids[self.pix[hit]] = self.face[hit]
        depth = self.zbuf.new_zeros(n).index_put((self.pix[hit],), self.zbuf[hit])  # one pair per pixel at most
        return face_ids.view(B, H, W), depth.view(B, H, W)


def check_blend_inputs(
    colors: torch.Tensor, fragments: Fragments, bg_table: torch.Tensor, pixels: int | None = None
) -> None:
    """The one shape check of a blend: ``colors`` (M, C), one colour per pair of ``fragments``, and ``bg_table``
    (P, C), one background colour per output pixel (``pixels``; default B * H * W of the fragments).

    Raises:
        unicorn.checks.ShapeError: names the argument and the shape it must have (TypeError: not a tensor, or
            ``colors`` and ``bg_table`` of another dtype than the fragments' barycentrics).
    """
    H, W = fragments.image_size
    dims = {"M": fragments.pix.shape[0], "P": fragments.batch_size * H * W if pixels is None else pixels}
    check_shape(colors, "M, C", "colors", dims, floating=True)
    check_shape(bg_table, "P, C", "bg_table", dims, floating=True)
    check_same_dtype(colors, fragments.bary, "colors", "fragments.bary")  # blends add the two: no silent promotion
    check_same_dtype(bg_table, fragments.bary, "bg_table", "fragments.bary")
