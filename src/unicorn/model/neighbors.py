"""Memory bank and viewpoint-binned nearest-neighbour search for the neighbour reconstruction loss."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from unicorn.geometry.rotations import rotation_angle_between

__all__ = ["NeighborMatch", "NeighborMemory"]


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
    """FIFO of the last ``size`` instances (images, masked shape / texture codes, hard-selected rotations).

    Viewpoint bins split ``[min_angle, max_angle]`` (degrees of relative rotation between the query's and an
    entry's predicted rotations) into ``n_bins`` equal ranges; the last bin includes ``max_angle``. The
    arccos is clamped, a query never matches its own entry, and a query whose drawn bin is empty draws
    again among its non-empty bins (equivalently: a bin drawn uniformly among the non-empty ones).

    The memory is not part of any state dict; :meth:`state` / :meth:`load_state` let a trainer save it.

    Args:
        size: capacity M (1024).
        n_bins: number of viewpoint bins V (5).
        min_angle, max_angle: angle range covered by the bins (20, 180).
    """

    _FIELDS = ("images", "shape_codes", "texture_codes", "R")

    def __init__(self, size: int = 1024, n_bins: int = 5, min_angle: float = 20.0, max_angle: float = 180.0) -> None:
        if size < 1 or n_bins < 1 or not 0 <= min_angle < max_angle <= 180:
            raise ValueError(
                f"invalid memory settings: size={size}, n_bins={n_bins}, angles=[{min_angle}, {max_angle}]"
            )
        self.size, self.n_bins = int(size), int(n_bins)
        self.min_angle, self.max_angle = float(min_angle), float(max_angle)
        self.images: torch.Tensor | None = None
        self.shape_codes: torch.Tensor | None = None
        self.texture_codes: torch.Tensor | None = None
        self.R: torch.Tensor | None = None

    def __len__(self) -> int:
        return 0 if self.R is None else self.R.shape[0]

    def clear(self) -> None:
        for name in self._FIELDS:
            setattr(self, name, None)

    def push(
        self, images: torch.Tensor, shape_codes: torch.Tensor, texture_codes: torch.Tensor, R: torch.Tensor
    ) -> torch.Tensor:
        """Append a batch (detached) and drop the oldest entries beyond ``size``.

        Args:
            images: (B, 3, H, W); shape_codes: (B, Cs); texture_codes: (B, Ct); R: (B, 3, 3).

        Returns:
            (B,) memory indices of the new entries (the last B rows; B must not exceed ``size``).
        """
        B = images.shape[0]
        if not (shape_codes.shape[0] == texture_codes.shape[0] == R.shape[0] == B) or R.shape[1:] != (3, 3):
            raise ValueError("images, codes and R (B, 3, 3) must share the batch size")
        if B > self.size:
            raise ValueError(f"batch of {B} does not fit a memory of {self.size}")
        new = {"images": images, "shape_codes": shape_codes, "texture_codes": texture_codes, "R": R}
        for name, value in new.items():
            old = getattr(self, name)
            value = value.detach()
            if old is not None:
                old = old.to(value.device)  # the model may have moved since the last push
            if old is not None and old.shape[1:] != value.shape[1:]:
                raise ValueError(f"memory field {name} holds {tuple(old.shape[1:])}, got {tuple(value.shape[1:])}")
            merged = value if old is None else torch.cat([old, value])
            setattr(self, name, merged[-self.size :])
        return torch.arange(len(self) - B, len(self), device=R.device)

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
        if len(self) == 0:
            raise RuntimeError("the neighbour memory is empty; push a batch first")
        B = R.shape[0]
        angles = rotation_angle_between(self.R.unsqueeze(1), R.unsqueeze(0))  # (M, B)
        entry_bins = self.bin_of(angles)
        usable = entry_bins >= 0
        if self_index is not None:
            usable[self_index, torch.arange(B, device=R.device)] = False
        # which bins hold at least one usable entry, per query: (B, n_bins)
        onehot = torch.nn.functional.one_hot(entry_bins.clamp(min=0), self.n_bins).bool() & usable.unsqueeze(-1)
        nonempty = onehot.any(0)
        valid = nonempty.any(1)
        weights = nonempty.float()
        weights[~valid] = 1.0  # placeholder row, ignored below
        # drawn where the weights are (no host round trip) unless the caller's generator lives elsewhere
        on = weights if generator is None or generator.device == weights.device else weights.cpu()
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

    def state(self) -> dict[str, torch.Tensor | None]:
        """The stored tensors, for saving with a training checkpoint."""
        return {name: getattr(self, name) for name in self._FIELDS}

    def load_state(self, state: dict[str, torch.Tensor | None]) -> None:
        """Restore tensors saved by :meth:`state`."""
        for name in self._FIELDS:
            setattr(self, name, state.get(name))
