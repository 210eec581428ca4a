"""What every unicorn dataset shares: the item layout, the placeholder pose and the bad-file policy.

Every item is a dict with at least

- ``image``: (3, H, W) float32 in [0, 1],
- ``mask``: (1, H, W) float32 in {0, 1} (all ones with ``has_mask`` False when the dataset has no masks),
- ``R``: (3, 3) and ``T``: (3,) float32, world-to-view ``x_view = x_world @ R + T``; where the dataset has no
  ground-truth camera they are the identity and ``(0, 0, 2.732)`` (UNICORN's prior translation) and
  ``has_pose`` is False,
- ``has_pose``, ``has_mask``: bool tensors (0-dim),
- ``index``: the dataset index (int64 tensor).

Datasets add ``points`` / ``normals`` (P, 3), ``keypoints`` (K, 3) and others where they exist.
"""

from __future__ import annotations

import logging
import warnings
from typing import Any, Literal

import numpy as np
import torch
from torch.utils.data import Dataset

from unicorn.data.images import DatasetError, ImageLoadError
from unicorn.errors import UnicornWarning, UserError

__all__ = [
    "PRIOR_TRANSLATION",
    "OnError",
    "SkippedFileWarning",
    "UnicornDataset",
    "UnreadableItemsError",
    "dummy_pose",
    "item_rng",
]

log = logging.getLogger(__name__)

#: UNICORN's prior camera translation, the distance of the NMR cameras.
PRIOR_TRANSLATION = (0.0, 0.0, 2.732)

OnError = Literal["skip", "raise"]


class UnreadableItemsError(UserError, RuntimeError):
    """Too many consecutive items of a dataset could not be read, even when skipping bad files."""


class SkippedFileWarning(UnicornWarning, RuntimeWarning):
    """An unreadable file (or malformed annotation records) that a dataset with ``on_error="skip"`` skips (once per
    file); the command-line programs log it in one line, into a run's ``train.log`` too
    (:func:`unicorn.cli.errors.log_warnings`)."""


def dummy_pose() -> tuple[torch.Tensor, torch.Tensor]:
    """Identity rotation (3, 3) and the prior translation (3,), for datasets without ground-truth cameras."""
    return torch.eye(3), torch.tensor(PRIOR_TRANSLATION)


def item_rng() -> np.random.Generator:
    """A numpy generator seeded from torch's RNG, so augmentation follows ``seed_everything`` and workers."""
    return np.random.default_rng(int(torch.randint(0, 2**62, (1,)).item()))


class UnicornDataset(Dataset):
    """Base class: subclasses implement ``__len__`` and ``load(index)``.

    ``__getitem__`` applies the bad-file policy: with ``on_error="raise"`` an unreadable image raises
    :class:`~unicorn.data.images.ImageLoadError` naming the file; with ``"skip"`` it warns once per file
    (:class:`SkippedFileWarning`) and returns the next readable item instead (so batch sizes stay fixed).
    """

    #: how many consecutive unreadable items to skip before giving up
    max_skips = 50
    #: whether items are drawn at random (box jitter, flips); subclasses that augment set it per instance
    augment = False

    def __init__(self, on_error: OnError = "raise") -> None:
        if on_error not in ("skip", "raise"):
            raise ValueError(f"on_error must be 'skip' or 'raise', got {on_error!r}")
        self.on_error = on_error
        self.bad_files: set[str] = set()
        self._items: dict[int, dict[str, Any]] | None = None

    def cache_items(self) -> None:
        """Keep every item in memory once read, so that each file is decoded once per process.

        For small datasets read many times (the synthetic default's 32 px images: decoding them costs about a
        twentieth of a CPU training step); the memory is that of the items (a 64 px item with its mask about
        64 KB). Items drawn at random cannot be cached.

        Raises:
            DatasetError: if this dataset augments its items.
        """
        if self.augment:
            raise DatasetError(f"{type(self).__name__} augments its items at random: they cannot be cached")
        if self._items is None:
            self._items = {}

    def load(self, index: int) -> dict[str, Any]:
        raise NotImplementedError

    def __getitem__(self, index: int) -> dict[str, Any]:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for a dataset of {n} items")
        index %= n
        if self._items is not None and index in self._items:
            return _copy_item(self._items[index])
        last_error: ImageLoadError | None = None
        for attempt in range(min(self.max_skips, n)):
            i = (index + attempt) % n
            try:
                item = self.load(i)
            except ImageLoadError as err:
                if self.on_error == "raise":
                    raise
                if err.path not in self.bad_files:
                    self.bad_files.add(err.path)
                    warnings.warn(f"skipping unreadable file: {err}", SkippedFileWarning, stacklevel=2)
                last_error = err
                continue
            item.setdefault("index", torch.tensor(i, dtype=torch.int64))
            if self._items is not None:
                self._items[index] = _copy_item(item)
            return item
        raise UnreadableItemsError(
            f"{min(self.max_skips, n)} consecutive unreadable items from index {index}, the last: {last_error}"
        ) from last_error


def _copy_item(item: dict[str, Any]) -> dict[str, Any]:
    # tensors copied too: a caller changing its item in place must not change the cached one
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in item.items()}
