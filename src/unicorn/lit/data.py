"""Iteration-based training data: an endless, resumable stream of shuffled batches.

UNICORN trains for a number of iterations, not epochs. :class:`StreamBatchSampler` yields batch ``b`` of an
endless concatenation of seeded permutations of the dataset, so the batches of a run are a pure function of
``(seed, b)``: resuming at iteration ``N`` only needs ``N`` (Lightning's restored ``global_step``), whatever the
number of workers or what had been prefetched when the checkpoint was written. Each rank of a distributed run
reads its own slice of every global batch. :class:`SeededItems` makes random augmentation a pure function of
the sample's stream position too, so a resumed run sees the very same augmented images.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

__all__ = ["IterationDataModule", "SeededItems", "StreamBatchSampler"]

_SEED_STRIDE = 1_000_003


class StreamBatchSampler(Sampler[list[tuple[int, int]]]):
    """Endless batches of ``(position, index)`` pairs over a dataset of ``n`` items.

    Position ``p`` of the stream holds item ``perm_e[p % n]`` with ``e = p // n`` and ``perm_e`` a permutation
    drawn from ``seed`` and ``e``. Global batch ``b`` covers positions ``[b W B, (b + 1) W B)`` for ``W`` ranks
    of ``B`` items; rank ``r`` takes the ``r``-th block of ``B``.

    Args:
        n: dataset size (>= 1).
        batch_size: per-rank batch size B.
        seed: shuffling seed.
        start_batch: first global batch to yield (the iterations already done when resuming).
        rank, world_size: this process's slice.
    """

    def __init__(
        self, n: int, batch_size: int, seed: int = 0, start_batch: int = 0, rank: int = 0, world_size: int = 1
    ) -> None:
        if n < 1 or batch_size < 1 or not 0 <= rank < world_size or start_batch < 0:
            raise ValueError(f"bad stream: n={n}, batch_size={batch_size}, rank={rank}/{world_size}")
        self.n, self.batch_size, self.seed = int(n), int(batch_size), int(seed)
        self.start_batch, self.rank, self.world_size = int(start_batch), int(rank), int(world_size)
        self._epoch, self._perm = -1, torch.empty(0, dtype=torch.long)

    def index_at(self, position: int) -> int:
        """Dataset index at a stream position."""
        epoch = position // self.n
        if epoch != self._epoch:
            g = torch.Generator().manual_seed(self.seed * _SEED_STRIDE + epoch)
            self._epoch, self._perm = epoch, torch.randperm(self.n, generator=g)
        return int(self._perm[position % self.n])

    def batch_at(self, batch: int) -> list[tuple[int, int]]:
        """This rank's ``(position, index)`` pairs of global batch ``batch``."""
        first = (batch * self.world_size + self.rank) * self.batch_size
        return [(p, self.index_at(p)) for p in range(first, first + self.batch_size)]

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        batch = self.start_batch
        while True:
            yield self.batch_at(batch)
            batch += 1


class SeededItems(Dataset):
    """Wraps a dataset indexed by ``(position, index)``: item ``index`` drawn with the torch RNG seeded from the
    stream position, so random augmentation (which draws from torch's global generator) is reproducible. The
    caller's RNG state is restored afterwards."""

    def __init__(self, dataset: Dataset, seed: int = 0) -> None:
        self.dataset, self.seed = dataset, int(seed)

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, key: tuple[int, int]) -> Any:
        position, index = key
        with torch.random.fork_rng(devices=[]):
            # the CPU generator only (what fork_rng restores): torch.manual_seed would also queue a lazy CUDA
            # seeding, with a stack trace, for every item (5 % of a CPU training step)
            torch.default_generator.manual_seed((self.seed + 1) * _SEED_STRIDE + position)
            return self.dataset[index]


class IterationDataModule(L.LightningDataModule):
    """Wraps a :class:`~unicorn.data.datamodule.UnicornDataModule`: the same splits and validation loader, and an
    endless resumable training stream (:class:`StreamBatchSampler`) starting at the trainer's ``global_step``.

    The trainer must run with ``use_distributed_sampler=False`` (the stream shards itself).

    Args:
        data: the dataset module (its ``train_set`` is read after ``setup``).
        seed: stream seed (the run's seed).
    """

    def __init__(self, data: L.LightningDataModule, seed: int = 0) -> None:
        super().__init__()
        self.data, self.seed = data, int(seed)

    def prepare_data(self) -> None:
        self.data.prepare_data()

    def setup(self, stage: str) -> None:
        self.data.setup(stage)
        train = getattr(self.data, "train_set", None)
        if stage == "fit" and (train is None or len(train) == 0):
            name = getattr(self.data, "name", type(self.data).__name__)
            root = getattr(self.data, "root", None)
            raise RuntimeError(f"dataset {name!r} (root {root!r}) has no training images")

    def train_dataloader(self) -> DataLoader:
        trainer = self.trainer
        start, rank, world = (
            (0, 0, 1) if trainer is None else (trainer.global_step, trainer.global_rank, trainer.world_size)
        )
        train = self.data.train_set  # type: ignore[attr-defined]
        workers = int(getattr(self.data, "num_workers", 0))
        sampler = StreamBatchSampler(len(train), self.data.batch_size, self.seed, start, rank, world)  # type: ignore
        return DataLoader(
            SeededItems(train, self.seed),
            batch_sampler=sampler,
            num_workers=workers,
            pin_memory=bool(getattr(self.data, "pin_memory", False)),
            persistent_workers=workers > 0,
            # a private generator: creating the iterator must not consume the global RNG
            generator=torch.Generator().manual_seed(self.seed),
        )

    def val_dataloader(self) -> DataLoader:
        return self.data.val_dataloader()
