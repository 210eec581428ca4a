"""The neighbour reconstruction loss (:class:`NeighborLoss`) and its memory bank with viewpoint-binned
nearest-neighbour search (:class:`NeighborMemory`): training state, owned by the trainer."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import nn

from unicorn.geometry.rotations import rotation_angle_between
from unicorn.hostsync import draw_device, is_sync_free
from unicorn.model import Prediction3D, Unicorn, world_verts
from unicorn.objectives.losses import ReconstructionLoss
from unicorn.render.precision import full_precision, to_full_precision

__all__ = ["NeighborLoss", "NeighborMatch", "NeighborMemory"]


@dataclass
class NeighborMatch:
    """Result of :meth:`NeighborMemory.search` for a batch of B queries.

    Attributes:
        shape_index: (B,) memory index of the nearest shape code in the drawn bin.
        texture_index: (B,) memory index of the nearest texture code in the same bin.
        bins: (B,) drawn viewpoint bin (-1 where none could be drawn).
        valid: (B,) False where no memory entry (other than the query itself) lies in any bin; the indices
            of those queries are 0 and must not be used.
    """

    shape_index: torch.Tensor
    texture_index: torch.Tensor
    bins: torch.Tensor
    valid: torch.Tensor


class NeighborMemory:
    """The last ``size`` instances (images, masked shape / texture codes, hard-selected rotations), first in first out.

    Viewpoint bins split ``[min_angle, max_angle]`` (degrees of relative rotation between the query's and an
    entry's predicted rotations) into ``n_bins`` equal ranges; the last bin includes ``max_angle``. The
    arccos is clamped, a query never matches its own entry, and a query whose drawn bin is empty draws
    again among its non-empty bins (equivalently: a bin drawn uniformly among the non-empty ones).

    The entries live in a ring of ``size`` rows allocated at the first push and written in place, each push from row
    :attr:`head` on, the oldest rows first: a compiled step finds the same tensors at every call (CUDA graphs
    replay only on the same addresses) and reads nothing on the host. :attr:`filled` marks the rows written so far.
    The memory is not part of any state dict; :meth:`state` / :meth:`load_state` let a trainer save it.

    Args:
        size: capacity M (1024).
        n_bins: number of viewpoint bins V (5).
        min_angle, max_angle: angle range covered by the bins (20, 180).
    """

    _FIELDS = ("images", "shape_codes", "texture_codes", "R")
    #: what :meth:`state` saves: the entries' fields, then the rows written and the next row
    _STATE = (*_FIELDS, "filled", "head")

    def __init__(self, size: int = 1024, n_bins: int = 5, min_angle: float = 20.0, max_angle: float = 180.0) -> None:
        if size < 1 or n_bins < 1 or not 0 <= min_angle < max_angle <= 180:
            raise ValueError(
                f"invalid memory settings: size={size}, n_bins={n_bins}, angles=[{min_angle}, {max_angle}]"
            )
        self.size, self.n_bins = int(size), int(n_bins)
        self.min_angle, self.max_angle = float(min_angle), float(max_angle)
        #: (M, 3, H, W), (M, Cs), (M, Ct) and (M, 3, 3) rows, None before the first push
        self.images: torch.Tensor | None = None
        self.shape_codes: torch.Tensor | None = None
        self.texture_codes: torch.Tensor | None = None
        self.R: torch.Tensor | None = None
        #: (M,) rows written so far; () the row the next push starts at
        self.filled: torch.Tensor | None = None
        self.head: torch.Tensor | None = None
        # what the last push overwrote (see undo_push)
        self._undo: tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor, torch.Tensor] | None = None

    def __len__(self) -> int:
        """The number of entries (a host read)."""
        return 0 if self.filled is None else int(self.filled.sum())

    def clear(self) -> None:
        for name in self._STATE:
            setattr(self, name, None)
        self._undo = None

    def push(
        self, images: torch.Tensor, shape_codes: torch.Tensor, texture_codes: torch.Tensor, R: torch.Tensor
    ) -> torch.Tensor:
        """Write a batch (detached) over the oldest entries.

        Args:
            images: (B, 3, H, W); shape_codes: (B, Cs); texture_codes: (B, Ct); R: (B, 3, 3).

        Returns:
            (B,) memory rows of the new entries (B must not exceed ``size``).
        """
        B = images.shape[0]
        if not (shape_codes.shape[0] == texture_codes.shape[0] == R.shape[0] == B) or R.shape[1:] != (3, 3):
            raise ValueError("images, codes and R (B, 3, 3) must share the batch size")
        if B > self.size:
            raise ValueError(f"batch of {B} does not fit a memory of {self.size}")
        # float32 under autocast too: the same state in checkpoints
        new = {"images": images, "shape_codes": shape_codes, "texture_codes": texture_codes, "R": R}
        new = {name: to_full_precision(value.detach()) for name, value in new.items()}
        if self.R is None:
            self._allocate({name: value[:0] for name, value in new.items()})
        elif self.R.device != R.device:  # a state loaded on another device
            self.to(R.device)
        stored = self.state(copy=False)
        for name, value in new.items():
            if stored[name].shape[1:] != value.shape[1:]:
                raise ValueError(
                    f"memory field {name} holds {tuple(stored[name].shape[1:])}, got {tuple(value.shape[1:])}"
                )
        assert self.filled is not None and self.head is not None
        rows = (self.head + torch.arange(B, device=R.device)) % self.size
        self._undo = (rows, {name: stored[name][rows] for name in self._FIELDS}, self.filled[rows], self.head.clone())
        for name, value in new.items():
            stored[name].index_copy_(0, rows, value.to(stored[name].dtype))
        self.filled.index_fill_(0, rows, True)
        self.head.copy_((self.head + B) % self.size)
        return rows

    def undo_push(self) -> None:
        """Put back what the last push overwrote (nothing if there was no push since the last :meth:`undo_push` or
        :meth:`forget_push`): the finite-loss check undoes an iteration that went wrong."""
        if self._undo is None or self.filled is None or self.head is None:
            return
        rows, before, filled, head = self._undo
        for name, value in before.items():
            getattr(self, name).index_copy_(0, rows, value)
        self.filled.index_copy_(0, rows, filled)
        self.head.copy_(head)
        self._undo = None

    def forget_push(self) -> None:
        """Keep the entries as they are: a later :meth:`undo_push` undoes only the pushes after this call."""
        self._undo = None

    def _allocate(self, like: dict[str, torch.Tensor]) -> None:
        """Rows of zeros for ``size`` entries shaped and typed as the (0, ...) tensors ``like``, none filled."""
        for name, value in like.items():
            setattr(self, name, value.new_zeros((self.size, *value.shape[1:])))
        device = like["R"].device
        self.filled = torch.zeros(self.size, dtype=torch.bool, device=device)
        self.head = torch.zeros((), dtype=torch.long, device=device)

    def to(self, device: torch.device | str) -> NeighborMemory:
        """Move the stored tensors to ``device`` (nothing copied where they are already there); returns self."""
        live = self.state(copy=False)
        moved = {name: None if t is None else t.to(device) for name, t in live.items()}
        if any(moved[name] is not t for name, t in live.items()):
            for name, value in moved.items():
                setattr(self, name, value)
            self._undo = None
        return self

    def bin_of(self, angles: torch.Tensor) -> torch.Tensor:
        """Viewpoint bin of relative angles (degrees), -1 outside ``[min_angle, max_angle]``."""
        width = (self.max_angle - self.min_angle) / self.n_bins
        bins = torch.floor((angles - self.min_angle) / width).long().clamp(max=self.n_bins - 1)
        outside = (angles < self.min_angle) | (angles > self.max_angle) | torch.isnan(angles)
        return torch.where(outside, torch.full_like(bins, -1), bins)

    @torch.no_grad()
    def search(
        self,
        shape_codes: torch.Tensor,
        texture_codes: torch.Tensor,
        R: torch.Tensor,
        self_index: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> NeighborMatch:
        """Nearest shape and texture neighbours of B queries inside one random viewpoint bin per query.

        Args:
            shape_codes: (B, Cs) and texture_codes: (B, Ct) masked codes of the queries.
            R: (B, 3, 3) predicted rotations of the queries.
            self_index: (B,) memory index of each query's own entry (from :meth:`push`), never returned.
            generator: optional random generator for the bin draw.
        """
        if self.R is None:  # no host read: a pushed memory holds at least one batch
            raise RuntimeError("the neighbour memory is empty; push a batch first")
        with full_precision(R.device.type):  # angles and distances in float32 under autocast too
            return self._search(shape_codes, texture_codes, R, self_index, generator)

    def _search(
        self,
        shape_codes: torch.Tensor,
        texture_codes: torch.Tensor,
        R: torch.Tensor,
        self_index: torch.Tensor | None,
        generator: torch.Generator | None,
    ) -> NeighborMatch:
        angles = rotation_angle_between(self.R.unsqueeze(1), R.unsqueeze(0))  # (M, B)
        entry_bins = self.bin_of(angles)
        usable = (entry_bins >= 0) & self.filled.unsqueeze(1)
        if self_index is not None:  # a comparison, not an assignment of a host scalar: nothing copied to the device
            usable &= torch.arange(usable.shape[0], device=R.device).unsqueeze(1) != self_index.unsqueeze(0)
        # which bins hold at least one usable entry, per query: (B, n_bins)
        # a comparison, not one_hot: one_hot reads the bins' range back on the CPU
        bin_ids = torch.arange(self.n_bins, device=R.device)
        onehot = (entry_bins.clamp(min=0).unsqueeze(-1) == bin_ids) & usable.unsqueeze(-1)
        nonempty = onehot.any(0)
        valid = nonempty.any(1)
        weights = torch.where(valid.unsqueeze(1), nonempty.float(), 1.0)  # a placeholder row where invalid
        on = weights.to(draw_device(weights.device, generator))
        bins = torch.multinomial(on, 1, generator=generator).squeeze(1).to(R.device)
        bins = torch.where(valid, bins, torch.full_like(bins, -1))
        candidate = usable & (entry_bins == bins.unsqueeze(0))  # (M, B)

        def nearest(memory: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
            dist = torch.cdist(
                memory.flatten(1).float(),
                queries.flatten(1).float(),
                compute_mode="donot_use_mm_for_euclid_dist",
            ).pow(2)  # (M, B)
            dist = dist.masked_fill(~candidate, float("inf"))
            return torch.where(valid, dist.argmin(0), torch.zeros_like(bins))

        return NeighborMatch(
            shape_index=nearest(self.shape_codes, shape_codes),
            texture_index=nearest(self.texture_codes, texture_codes),
            bins=bins,
            valid=valid,
        )

    def state(self, copy: bool = True) -> dict[str, torch.Tensor | None]:
        """The stored tensors (the entries' fields, ``filled`` and ``head``; None before the first push), for saving
        with a training checkpoint: copies, unless ``copy`` is False (the live tensors, which pushes change in place).
        """
        tensors = {name: getattr(self, name) for name in self._STATE}
        if copy:
            tensors = {name: None if t is None else t.clone() for name, t in tensors.items()}
        return tensors

    def load_state(self, state: Mapping[str, torch.Tensor | None]) -> None:
        """Restore tensors saved by :meth:`state`, into the tensors the memory holds where they have the same shape,
        type and device (a compiled step's graphs keep their inputs).

        A state without ``head`` holds its entries in rows ``0 .. n-1``, oldest first (n <= ``size``; the newest
        ``size`` of more), the next push writing row ``n``; so does a state whose ring has another size.
        """
        if state.get("R") is None:
            self.clear()
            return
        state = _ring(state, self.size)
        live = self.state(copy=False)
        for name, value in state.items():
            have = live.get(name)
            if have is not None and (have.shape, have.dtype, have.device) == (value.shape, value.dtype, value.device):
                have.copy_(value)
            else:
                setattr(self, name, value.clone())
        self._undo = None


def _ring(state: Mapping[str, torch.Tensor | None], size: int) -> dict[str, torch.Tensor]:
    """``state`` (:meth:`NeighborMemory.state`) as a ring of ``size`` rows: unchanged when it is one, else its
    entries oldest first in rows ``0 .. n-1`` (the newest ``size`` of them), with ``head`` at row ``n``."""
    fields = {name: state.get(name) for name in NeighborMemory._FIELDS}
    if any(value is None for value in fields.values()):
        raise ValueError(f"a neighbour memory state needs {', '.join(NeighborMemory._FIELDS)}")
    filled, head = state.get("filled"), state.get("head")
    if filled is not None and head is not None and filled.shape[0] == size:
        return {**fields, "filled": filled, "head": head}
    if filled is not None and head is not None:  # another size: its entries, oldest first
        order = torch.roll(torch.arange(filled.shape[0], device=filled.device), -int(head))
        order = order[filled[order]]
        fields = {name: value[order] for name, value in fields.items()}
    n = min(fields["R"].shape[0], size)
    device = fields["R"].device
    ring = {name: value.new_zeros((size, *value.shape[1:])) for name, value in fields.items()}
    for name, value in fields.items():
        ring[name][:n] = value[value.shape[0] - n :]
    filled = torch.arange(size, device=device) < n
    return {**ring, "filled": filled, "head": torch.tensor(n % size, device=device)}


@dataclass
class _Neighbours:
    """What the two swaps take from n shape neighbours and n texture neighbours (see :meth:`NeighborLoss.forward`):
    the shape neighbours' scales (n, 3) and textures (n, 3, Ht, Wt), the texture neighbours' world meshes
    (n, V, 3), and everyone's R (2n, 3, 3), T (2n, 3) and background (2n, 3, S, S) or None."""

    scale: torch.Tensor
    texture: torch.Tensor
    verts: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    background: torch.Tensor | None


def _neighbours(model: Unicorn, images: torch.Tensor, n: int, average_texture: bool | torch.Tensor) -> _Neighbours:
    """The swaps' parameters from ``images`` (2n, 3, S, S): the n shape neighbours then the n texture neighbours.

    The encoders see all 2n images together (their batch statistics are those of :meth:`Unicorn.predict` on the
    same batch); the heads compute only what a swap uses. Call without gradient.
    """
    feats = model.encode(images, model.branches())
    scale = model.scale(feats["shape"])
    z_bg = None if model.background is None else model.background.code(feats["background"])
    canonical, maps, bkg = model.decode(
        model.shape.code(feats["shape"][n:]), model.texture.code(feats["texture"][:n]), z_bg, average_texture
    )
    verts = world_verts(canonical, scale[n:])
    R, T = model.pose(feats["pose"]).select()
    return _Neighbours(scale[:n], maps, verts, R, T, bkg)


class NeighborLoss(nn.Module):
    """Weighted neighbour reconstruction per sample (B,), with the memory bank it fills.

    The batch is pushed to the memory first. For each sample a viewpoint bin is drawn and the nearest shape and
    texture neighbours in it are found; their parameters are recomputed with the current network without
    gradient. Swap 1 renders this sample's shape (with gradient) with the shape neighbour's scale, texture, pose
    and background; swap 2 renders the texture neighbour's mesh with this sample's texture (with gradient). Each
    is compared with the neighbour's image. Samples without a neighbour score 0.

    Args:
        reconstruction: the weighted per-sample reconstruction terms.
        memory: the memory bank.
        weight: weight of the loss (<= 0: never active).
    """

    def __init__(self, reconstruction: ReconstructionLoss, memory: NeighborMemory, weight: float) -> None:
        super().__init__()
        self.reconstruction, self.memory, self.weight = reconstruction, memory, weight

    def _apply(self, fn: Callable[[torch.Tensor], torch.Tensor], recurse: bool = True) -> NeighborLoss:
        super()._apply(fn, recurse)
        # the memory is no buffer (a trainer saves it, not the state dict) but follows the module's device, in
        # float32: moved here, not inside the first step after the move
        if self.memory.R is not None:
            self.memory.to(fn(torch.empty(0, device=self.memory.R.device)).device)
        return self

    def active(self, model: Unicorn) -> bool:
        """Whether the loss applies: a positive weight and active shape and texture code dimensions."""
        return self.weight > 0 and model.shape.mask.active_dims > 0 and model.texture.mask.active_dims > 0

    def forward(
        self,
        model: Unicorn,
        images: torch.Tensor,
        pred: Prediction3D,
        R: torch.Tensor,
        average_texture: bool | torch.Tensor = False,
    ) -> torch.Tensor:
        """The weighted loss (B,) of images (B, 3, S, S), their 3D prediction and hard-selected rotations (B, 3, 3).

        ``average_texture`` applies to the neighbours' textures as it did to ``pred``'s.
        """
        return self.weight * self._unweighted(model, images, pred, R, average_texture)

    def _unweighted(
        self,
        model: Unicorn,
        images: torch.Tensor,
        pred: Prediction3D,
        R: torch.Tensor,
        average_texture: bool | torch.Tensor,
    ) -> torch.Tensor:
        memory = self.memory
        self_index = memory.push(images, pred.shape_code, pred.texture_code, R)
        match = memory.search(pred.shape_code.detach(), pred.texture_code.detach(), R, self_index)
        loss = images.new_zeros(images.shape[0])
        if is_sync_free():
            # every sample swaps (those without neighbours with memory entry 0) and their loss is masked out: no
            # host read, the same loss as below whenever every sample found neighbours
            idx = torch.arange(images.shape[0], device=images.device)
            return torch.where(match.valid, self._swapped(model, images, pred, match, idx, average_texture), loss)
        # a host sync: the swaps run on the samples that found neighbours only (all of them once the memory
        # holds a few batches); padding the others would change the neighbour batch's BatchNorm statistics
        idx = match.valid.nonzero().squeeze(1)
        if idx.numel() == 0:
            return loss
        return loss.index_put((idx,), self._swapped(model, images, pred, match, idx, average_texture))

    def _swapped(
        self,
        model: Unicorn,
        images: torch.Tensor,
        pred: Prediction3D,
        match: NeighborMatch,
        idx: torch.Tensor,
        average_texture: bool | torch.Tensor,
    ) -> torch.Tensor:
        """The swap losses (n,) of the samples ``idx`` (n,): their shape with the neighbour's texture and the
        other way round, against the neighbours' images."""
        memory = self.memory
        assert memory.images is not None  # pushed above
        nbr_images = torch.cat([memory.images[match.shape_index[idx]], memory.images[match.texture_index[idx]]])
        n = idx.numel()
        with torch.no_grad():
            nbr = _neighbours(model, nbr_images, n, average_texture)
        verts = torch.cat([world_verts(pred.canonical_verts[idx], nbr.scale), nbr.verts])
        tex = torch.cat([nbr.texture, pred.texture[idx]])
        rec, _ = model.render(verts, tex, nbr.R, nbr.T, nbr.background)
        terms = self.reconstruction(rec, nbr_images)
        if not terms:
            return images.new_zeros(n)
        per = sum(terms.values())
        return per[:n] + per[n:]
