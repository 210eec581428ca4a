"""The LightningDataModule of every dataset: splits, validation subset, loaders, and the training stream.

:class:`UnicornDataModule` builds a dataset's splits with :mod:`unicorn.data.registry` (free of Lightning) and
serves their loaders. UNICORN trains for a number of iterations, not epochs: :class:`StreamBatchSampler` yields
batch ``b`` of an endless concatenation of seeded permutations of the dataset, so the batches of a run are a pure
function of ``(seed, b)``: resuming at iteration ``N`` only needs ``N`` (Lightning's restored ``global_step``),
whatever the number of workers or what had been prefetched when the checkpoint was written. Each rank of a
distributed run reads its own slice of every global batch. :class:`SeededItems` makes random augmentation a pure
function of the sample's stream position too, so a resumed run sees the very same augmented images.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, Subset

from unicorn.data.common import OnError
from unicorn.data.images import DatasetError, set_max_image_bytes, set_max_image_pixels
from unicorn.data.registry import Split, build_dataset, dataset_root, dataset_spec, prepare_dataset, val_indices
from unicorn.errors import ignore_stop_signals

__all__ = [
    "MAX_AUTO_WORKERS",
    "SeededItems",
    "StreamBatchSampler",
    "UnicornDataModule",
    "auto_num_workers",
    "usable_cpus",
]

_SEED_STRIDE = 1_000_003
#: the most DataLoader workers ``num_workers="auto"`` starts for one training process
MAX_AUTO_WORKERS = 16


def usable_cpus() -> int:
    """The CPU cores this process may run on (its affinity where the platform has one, else the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def auto_num_workers(device_type: str, cpus: int | None = None, processes: int = 1) -> int:
    """DataLoader workers per training process for ``num_workers="auto"``, chosen from the machine.

    Training on a GPU (``device_type="cuda"``): the CPU cores this process may use (``cpus``, default
    :func:`usable_cpus`), shared by the node's ``processes`` training processes, less one core for each training
    process itself; at least 1 and at most :data:`MAX_AUTO_WORKERS`. Training on the CPU: 0, the batches are loaded
    in the training process: its threads already use every core, and workers would take their time from them.

    Example:
        >>> auto_num_workers("cuda", cpus=16), auto_num_workers("cuda", cpus=16, processes=4), auto_num_workers("cpu")
        (15, 3, 0)
    """
    if device_type != "cuda":
        return 0
    cpus = usable_cpus() if cpus is None else int(cpus)
    return max(1, min(MAX_AUTO_WORKERS, cpus // max(int(processes), 1) - 1))


def _check_auto(value: Any, name: str, kind: type) -> None:
    """``value`` must be ``"auto"``, None (the same) or of ``kind`` (a bool is no count)."""
    if value is None or value == "auto":
        return
    if kind is int and isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return
    if kind is bool and isinstance(value, bool):
        return
    expected = "a number >= 0" if kind is int else "true or false"
    raise ValueError(f"{name} must be {expected}, 'auto' or None (chosen from the machine), got {value!r}")


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
        self._epoch, self._order = -1, []  # the epoch's permutation, as Python ints

    def index_at(self, position: int) -> int:
        """Dataset index at a stream position."""
        epoch = position // self.n
        if epoch != self._epoch:
            g = torch.Generator().manual_seed(self.seed * _SEED_STRIDE + epoch)
            self._epoch, self._order = epoch, torch.randperm(self.n, generator=g).tolist()
        return self._order[position % self.n]

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


class UnicornDataModule(L.LightningDataModule):
    """Train / val / test loaders for one dataset.

    The training loader is, with ``stream_seed`` (``unicorn-train`` passes the run's seed), an endless resumable
    stream (:class:`StreamBatchSampler`) starting at the trainer's ``global_step``; the trainer must then run with
    ``use_distributed_sampler=False`` (the stream shards itself). Without it, it is a shuffled loader of one pass
    over the training set, seeded by ``seed``.

    Args:
        name: a registered dataset (:func:`~unicorn.data.registry.list_datasets`).
        root: dataset root; for ``synthetic`` the parent folder of generated datasets (default: the cache,
            ``$UNICORN_CACHE/synthetic`` or ``~/.cache/unicorn/synthetic``).
        categories: ShapeNet categories (names or synsets); for ``synthetic`` the generated categories.
        img_size: image side.
        batch_size: training batch size (evaluation uses the same).
        num_workers: DataLoader worker processes; ``"auto"`` or None: chosen from the machine when the loaders
            are made (:func:`auto_num_workers`: on a GPU one per CPU core of the training process less one, at
            most :data:`MAX_AUTO_WORKERS`; on the CPU none). Workers stay alive between passes (persistent).
        seed: seeds the one-pass training shuffle and the evaluation view choice.
        val_size: validation subset size, default :data:`~unicorn.data.registry.VAL_SIZES` (capped at the split
            size).
        on_error: ``"raise"`` or ``"skip"`` unreadable images.
        pin_memory: pin batches in page-locked memory, for faster and asynchronous copies to a GPU; ``"auto"`` or
            None: when training on CUDA.
        cache_items: keep the training items in memory once read (:meth:`UnicornDataset.cache_items
            <unicorn.data.common.UnicornDataset.cache_items>`; datasets without augmentation only, e.g. the
            synthetic default). Each worker process holds its own copy. Validation and test items (read a few
            times, and with their point clouds) are not cached.
        synthetic: for ``synthetic``: ``mode`` (``"nmr"``/``"wild"``), ``n_models``, ``seed`` and other
            :func:`~unicorn.data.synthetic.writer.generate_synthetic_dataset` options.
        options: extra dataset-constructor arguments (e.g. ``{"tag": "horse"}`` for LSUN).
        max_image_pixels: refuse images with more pixels (a bad image, skipped with ``on_error="skip"``); None:
            the current limit (:func:`unicorn.data.images.max_image_pixels`), 0: no limit. Set for the whole
            process and its workers.
        max_image_bytes: refuse images whose decoded array (width x height x bands x bytes per band, 12 bytes per
            pixel for float32 RGB) has more bytes, likewise; None: the current limit
            (:func:`unicorn.data.images.max_image_bytes`), 0: no limit.
        stream_seed: seed of the endless training stream; None: one-pass training loaders.
    """

    def __init__(
        self,
        name: str,
        root: str | None = None,
        categories: str | list[str] | None = None,
        img_size: int = 64,
        batch_size: int = 32,
        num_workers: int | Literal["auto"] | None = "auto",
        seed: int = 0,
        val_size: int | None = None,
        on_error: OnError = "raise",
        pin_memory: bool | Literal["auto"] | None = "auto",
        cache_items: bool = False,
        synthetic: dict[str, Any] | None = None,
        options: dict[str, Any] | None = None,
        max_image_pixels: int | None = None,
        max_image_bytes: int | None = None,
        stream_seed: int | None = None,
    ) -> None:
        super().__init__()
        _check_auto(num_workers, "num_workers", int)
        _check_auto(pin_memory, "pin_memory", bool)
        if max_image_pixels is not None:
            set_max_image_pixels(max_image_pixels)
        if max_image_bytes is not None:
            set_max_image_bytes(max_image_bytes)
        spec = dataset_spec(name)  # an unknown name fails here, naming the known ones
        if not spec.generated and root is None:
            raise DatasetError(f"dataset {name!r} needs a root folder (dataset.root)")
        self.name, self.root, self.img_size = name, root, int(img_size)
        # Hydra passes lists as ListConfig: normalise to plain str / list[str]
        if categories is None or isinstance(categories, str):
            self.categories = categories
        else:
            self.categories = [str(c) for c in categories]
        self.batch_size, self.seed = int(batch_size), int(seed)
        self.num_workers: int | Literal["auto"] = "auto" if num_workers in (None, "auto") else int(num_workers)
        self.pin_memory: bool | Literal["auto"] = "auto" if pin_memory in (None, "auto") else bool(pin_memory)
        self.val_size, self.on_error = val_size, on_error
        self.cache_items = bool(cache_items)
        self.synthetic = dict(synthetic or {})
        self.options = dict(options or {})
        self.stream_seed = None if stream_seed is None else int(stream_seed)
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None
        self.test_set: Dataset | None = None

    def dataset_root(self) -> Path:
        """Folder the datasets are read from (for ``synthetic``: the generated dataset)."""
        return dataset_root(self.name, self.root, self.categories, self.synthetic)

    def prepare_data(self) -> None:
        """Generate the synthetic dataset if it is absent (runs on one process only)."""
        prepare_dataset(self.name, self.root, self.categories, self.synthetic)

    def build(self, split: Split) -> Dataset:
        """The full dataset of ``split`` (see :func:`~unicorn.data.registry.build_dataset`)."""
        dataset = build_dataset(
            self.name,
            split,
            self.dataset_root(),
            img_size=self.img_size,
            categories=self.categories,
            seed=self.seed,
            on_error=self.on_error,
            **self.options,
        )
        if self.cache_items and split == "train":
            try:
                dataset.cache_items()  # type: ignore[attr-defined]
            except DatasetError as err:
                raise DatasetError(f"dataset.cache_items=true for {self.name} {split}: {err}") from None
        return dataset

    def check_early(self) -> None:
        """Build the training and validation sets of a dataset read from disk now (:meth:`setup` keeps them), so
        that a missing or malformed dataset is reported before the model is built and its VGG16 weights loaded; a
        generated dataset waits for :meth:`prepare_data`.

        Raises:
            unicorn.data.DatasetNotFoundError, unicorn.data.DatasetError: see :meth:`setup`.
        """
        if not dataset_spec(self.name).generated:
            self.setup("fit")

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit") and self.train_set is None:
            self.train_set = self.build("train")
        if stage == "fit" and self.stream_seed is not None and len(self.train_set) == 0:  # type: ignore[arg-type]
            raise DatasetError(f"dataset {self.name!r} (root {self.root!r}) has no training images")
        if stage in (None, "fit", "validate") and self.val_set is None:
            full = self.build("val")
            self.val_set = Subset(full, val_indices(self.name, len(full), self.val_size))
        if stage in (None, "test", "predict") and self.test_set is None:
            self.test_set = self.build("test")

    def loader_settings(self) -> tuple[int, bool]:
        """``(num_workers, pin_memory)`` of the loaders, ``"auto"`` resolved for the device the trainer trains on
        (without a trainer: CUDA where it is available) and its processes per node."""
        trainer = self.trainer
        if trainer is None:
            device_type, processes = ("cuda" if torch.cuda.is_available() else "cpu"), 1
        else:
            device_type, processes = trainer.strategy.root_device.type, max(int(trainer.num_devices), 1)
        workers = self.num_workers
        if workers == "auto":
            workers = auto_num_workers(device_type, processes=processes)
        pin = device_type == "cuda" if self.pin_memory == "auto" else bool(self.pin_memory)
        return int(workers), pin

    def _loader(self, dataset: Dataset | None, train: bool) -> DataLoader:
        if dataset is None:
            raise RuntimeError("call setup() before asking for a dataloader")
        workers, pin = self.loader_settings()
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            shuffle=train,
            drop_last=train and len(dataset) >= self.batch_size,  # type: ignore[arg-type]
            num_workers=workers,
            pin_memory=pin,
            persistent_workers=workers > 0,
            worker_init_fn=ignore_stop_signals,  # the run stops at a step boundary, its workers with it
            # a private generator: a validation during training must not consume the global RNG the training draws
            # from (the loader draws its workers' base seed at every pass)
            generator=torch.Generator().manual_seed(self.seed),
        )

    def _stream(self, dataset: Dataset | None, seed: int) -> DataLoader:
        if dataset is None:
            raise RuntimeError("call setup() before asking for a dataloader")
        trainer = self.trainer
        start, rank, world = (
            (0, 0, 1) if trainer is None else (trainer.global_step, trainer.global_rank, trainer.world_size)
        )
        sampler = StreamBatchSampler(len(dataset), self.batch_size, seed, start, rank, world)  # type: ignore[arg-type]
        workers, pin = self.loader_settings()
        return DataLoader(
            SeededItems(dataset, seed),
            batch_sampler=sampler,
            num_workers=workers,
            pin_memory=pin,
            persistent_workers=workers > 0,
            worker_init_fn=ignore_stop_signals,  # the run stops at a step boundary, its workers with it
            # a private generator: creating the iterator must not consume the global RNG
            generator=torch.Generator().manual_seed(seed),
        )

    def train_dataloader(self) -> DataLoader:
        if self.stream_seed is None:
            return self._loader(self.train_set, train=True)
        return self._stream(self.train_set, self.stream_seed)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, train=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.test_set, train=False)
