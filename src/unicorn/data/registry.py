"""The dataset registry: every dataset by name, its splits, the validation subset, the synthetic set's folder.

Dataset names: ``shapenet_nmr``, ``synthetic`` (generated on first use, then read as ShapeNet-NMR),
``cub_200``, ``p3d_car``, ``compcars``, ``lsun``, ``folder``. Splits follow the reference: ShapeNet uses the
SoftRas lists (training on every view, evaluation on one fixed random view per model); CUB its CMR splits;
Pascal3D+ car has train / test and validates on training images; CompCars, LSUN and folders have no split
(every image is used for training and testing). Validation runs on a small subset, as in the reference, capped
at the dataset size. The Lightning DataModule built on these is :class:`unicorn.lit.UnicornDataModule`.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from torch.utils.data import Dataset

from unicorn.data.common import OnError
from unicorn.data.cub import CUB200
from unicorn.data.folder import CompCars, ImageFolder
from unicorn.data.images import DatasetError, DatasetNotFoundError
from unicorn.data.lsun import LSUN
from unicorn.data.p3d import Pascal3DCar
from unicorn.data.shapenet import ShapeNetNMR
from unicorn.registry import Registry, check_options, keyword_options

__all__ = [
    "DATASETS",
    "DATASET_NAMES",
    "DatasetSpec",
    "SYNTHETIC_DEFAULTS",
    "VAL_SIZES",
    "Split",
    "build_dataset",
    "dataset_root",
    "dataset_spec",
    "list_datasets",
    "prepare_dataset",
    "register_dataset",
    "stored_image_size",
    "synthetic_options",
    "val_indices",
]


Split = Literal["train", "val", "test"]

#: the reference shuffles CUB's evaluation sets with this seed
_EVAL_SHUFFLE_SEED = 123
#: the reference's LSUN validation images start at this offset
_LSUN_VAL_OFFSET = 17
#: settings of a ``synthetic`` dataset left out of its config (the category when ``categories`` is None)
SYNTHETIC_DEFAULTS: dict[str, Any] = {"category": "chair", "mode": "nmr", "n_models": 200, "seed": 0}


def _first(n: int, size: int) -> list[int]:
    return list(range(size))


def _shuffled(n: int, size: int) -> list[int]:
    # NumPy's legacy generator, as the reference's np.random.seed(123) before np.random.shuffle: the same images
    return np.random.RandomState(_EVAL_SHUFFLE_SEED).permutation(n)[:size].tolist()


def _from_offset(n: int, size: int) -> list[int]:
    return list(range(_LSUN_VAL_OFFSET, _LSUN_VAL_OFFSET + size)) if n >= _LSUN_VAL_OFFSET + size else _first(n, size)


def _shapenet(root: Any, split: str, img_size: int, categories: Any, seed: int, on_error: OnError, **o: Any) -> Dataset:
    # every view for training, one fixed random view per model for evaluation, unless told
    views = o.pop("views", "all" if split == "train" else "random")
    dataset = ShapeNetNMR(root, categories, split, views=views, seed=seed, on_error=on_error, **o)
    _refuse_repeated_categories(categories, dataset.synsets)
    return dataset


def _refuse_repeated_categories(categories: Any, synsets: list[str]) -> None:
    """Refuse categories that name one category twice (by name, or by name and synset): its models would be read,
    trained on and scored twice.

    Raises:
        DatasetError: names the repeated category.
    """
    if categories is None:  # every category of the dataset, once each
        return
    given = [categories] if isinstance(categories, str) else list(categories)
    first: dict[str, Any] = {}
    for cat, synset in zip(given, synsets, strict=True):  # one synset per category given, in order
        if synset not in first:
            first[synset] = cat
            continue
        if cat == first[synset]:
            problem = f"category {cat!r} is named twice"
        else:
            problem = f"categories {first[synset]!r} and {cat!r} are one category (synset {synset})"
        raise DatasetError(f"{problem} in categories {given}; name each category once")


#: where the synthetic data comes from, in the message of a root that is not a generated dataset
_SYNTHETIC_HINT = (
    "unicorn-train generates it on first use in a folder under dataset.root (by default $UNICORN_CACHE/synthetic; "
    "$UNICORN_CACHE/synthetic_32px with +experiment=synthetic), and unicorn-data synth --out DIR with the run's "
    "dataset.synthetic settings generates it again"
)
#: the generated datasets a parent folder given as the root names in its message
_SHOWN_DATASETS = 3


def _synthetic(
    root: Any, split: str, img_size: int, categories: Any, seed: int, on_error: OnError, **o: Any
) -> Dataset:
    # the generated folder itself: ShapeNet-NMR's hint (download 33 GB) would not bring it back
    folder = Path(root).expanduser()
    if not folder.is_dir():
        raise DatasetNotFoundError(folder, "generated synthetic dataset", _SYNTHETIC_HINT)
    if not (folder / "metadata.yaml").exists():
        _refuse_parent_folder(folder)
        raise DatasetNotFoundError(
            folder / "metadata.yaml", "generated synthetic dataset's metadata.yaml", _SYNTHETIC_HINT
        )
    return _shapenet(root, split, img_size, categories, seed, on_error, **o)


def _refuse_parent_folder(folder: Path) -> None:
    """Refuse a folder that holds generated synthetic datasets (folders with a ``synthetic.json``) for one of them:
    a training run's ``dataset.root``, their parent.

    Raises:
        DatasetError: names the datasets in it (the first :data:`_SHOWN_DATASETS`) to give as the root instead.
    """
    try:
        found = sorted(
            child
            for child in folder.iterdir()
            if not child.name.startswith(".") and (child / "synthetic.json").is_file()
        )
    except OSError:  # an unreadable folder: the missing metadata.yaml is the message
        return
    if not found:
        return
    shown = ", ".join(str(path) for path in found[:_SHOWN_DATASETS])
    more = f" (and {len(found) - _SHOWN_DATASETS} more)" if len(found) > _SHOWN_DATASETS else ""
    raise DatasetError(
        f"{folder} is a folder of generated synthetic datasets (as a training run's dataset.root is), not one: give "
        f"one of them as the root: {shown}{more}"
    )


def _cub(root: Any, split: str, img_size: int, categories: Any, seed: int, on_error: OnError, **o: Any) -> Dataset:
    return CUB200(root, split, img_size=img_size, on_error=on_error, **o)


def _p3d(root: Any, split: str, img_size: int, categories: Any, seed: int, on_error: OnError, **o: Any) -> Dataset:
    # the reference validates on (unaugmented) training images
    p3d_split = "test" if split == "test" else "train"
    return Pascal3DCar(root, p3d_split, img_size=img_size, augment=split == "train", on_error=on_error, **o)


def _unsplit(cls: type) -> Callable[..., Dataset]:
    """A dataset without splits: every image for training (augmented) and for testing."""

    def build(root: Any, split: str, img_size: int, categories: Any, seed: int, on_error: OnError, **o: Any) -> Dataset:
        return cls(root, img_size=img_size, augment=split == "train", on_error=on_error, **o)

    return build


def _options(cls: type, *set_here: str) -> tuple[str, ...]:
    """The keyword arguments of a dataset class that are a user's options: all but ``set_here``, which the
    registry's builder sets."""
    return tuple(key for key in keyword_options(cls) or () if key not in set_here)


_SHAPENET_OPTIONS = _options(ShapeNetNMR, "root", "categories", "split", "seed", "on_error")
_UNSPLIT_SET = ("root", "img_size", "augment", "on_error")


def _stored_as_is(root: Any, categories: Any = None, synthetic: Any = None) -> Path:
    return Path(str(root))


def _no_stored_size(synthetic: Mapping[str, Any] | None) -> int | None:
    return None


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset: how to build a split, where it is read from, the validation subset, and what evaluation does
    with it.

    Attributes:
        build: ``(root, split, img_size, categories, seed, on_error, **options) -> Dataset``.
        val_size: the reference's validation subset size.
        protocol: the evaluation protocol (:mod:`unicorn.evaluation`): ``shapenet``, ``cub``, ``p3d``, ``images``.
        options: the names of the ``**options`` that ``build`` takes (the dataset class's other arguments).
        val_pick: ``(n, size) -> indices`` of the validation subset of a split of n items.
        eval_options: extra dataset options when evaluating (ground-truth points, the keypoint frame).
        folder: ``(root, categories, synthetic) -> Path``, the folder the dataset is read from (default: ``root``).
        prepare: ``(root, categories, synthetic) -> Path``, the folder after making the data where it is made on
            first use (default: :attr:`folder`; the data is read as it is).
        stored_size: ``(synthetic) -> int | None``, the side of the images as stored when the loader does not
            resize them to ``img_size`` (default: None).
        by_category: whether ``build`` picks the items by its ``categories`` argument (ShapeNet's synsets); the
            command-line tools refuse ``--categories`` for a dataset that does not.
        data_options: the options that say which data a run reads and how it is framed (LSUN's ``tag``, a folder's
            ``extensions``), not how training draws from it: the run's evaluations read the same data with them.
    """

    build: Callable[..., Dataset]
    val_size: int
    protocol: str
    options: tuple[str, ...] = ()
    val_pick: Callable[[int, int], list[int]] = _first
    eval_options: Mapping[str, Any] = field(default_factory=dict)
    folder: Callable[..., Path] = _stored_as_is
    prepare: Callable[..., Path] | None = None
    stored_size: Callable[[Mapping[str, Any] | None], int | None] = _no_stored_size
    by_category: bool = True
    data_options: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        """Refuse fields of the wrong kind when the entry is made (a plugin's mistake, said at its registration).

        Raises:
            TypeError: ``build`` is not callable, ``protocol`` not a name, or ``options`` not a sequence of names.
        """
        if not callable(self.build):
            raise TypeError(f"DatasetSpec.build must be a function (root, split, ...) -> dataset, got {self.build!r}")
        if not isinstance(self.protocol, str) or not self.protocol:
            raise TypeError(f"DatasetSpec.protocol must be a protocol's name, got {self.protocol!r}")
        if isinstance(self.options, str) or not all(isinstance(o, str) for o in self.options):
            raise TypeError(f"DatasetSpec.options must be a tuple of option names, got {self.options!r}")
        object.__setattr__(self, "options", tuple(self.options))  # frozen: set once, here

    @property
    def generated(self) -> bool:
        """Whether the data is made on first use (under a default folder: no root needed)."""
        return self.prepare is not None


def _synthetic_folder(root: Any, categories: Any = None, synthetic: Mapping[str, Any] | None = None) -> Path:
    # imported here: the generator pulls in open3d, which real-data training never needs
    from unicorn.data.synthetic.writer import synthetic_dataset_path

    args = synthetic_options(root, categories, synthetic)
    return synthetic_dataset_path(args["category"], args["mode"], args["n_models"], args["seed"], args["root"])


def _synthetic_prepare(root: Any, categories: Any = None, synthetic: Mapping[str, Any] | None = None) -> Path:
    from unicorn.data.synthetic.writer import ensure_synthetic_dataset

    options = synthetic_options(root, categories, synthetic)
    _check_generation_root(options["root"], bool(options.pop("generate", False)))
    return ensure_synthetic_dataset(**options)


def _synthetic_stored_size(synthetic: Mapping[str, Any] | None) -> int:
    from unicorn.data.synthetic.writer import generate_synthetic_dataset

    default = inspect.signature(generate_synthetic_dataset).parameters["image_size"].default
    return int(dict(synthetic or {}).get("image_size", default))


#: every dataset by name: the one list of names, validation sizes, protocols and folders
DATASETS: Registry[DatasetSpec] = Registry("dataset")
_SHAPENET = DatasetSpec(_shapenet, 32, "shapenet", _SHAPENET_OPTIONS, eval_options={"with_points": True})
DATASETS.add("shapenet_nmr", _SHAPENET)
# generated on first use, then read as ShapeNet-NMR
DATASETS.add(
    "synthetic",
    dataclasses.replace(
        _SHAPENET,
        build=_synthetic,
        folder=_synthetic_folder,
        prepare=_synthetic_prepare,
        stored_size=_synthetic_stored_size,
    ),
)
_CUB_OPTIONS = _options(CUB200, "root", "split", "img_size", "on_error")
# the datasets below hold one category each: their builds ignore ``categories``
DATASETS.add(
    "cub_200",
    DatasetSpec(_cub, 5, "cub", _CUB_OPTIONS, _shuffled, eval_options={"eval_size": 256}, by_category=False),
)
# the CAD clouds on every split evaluated (the validation images are training images, which go without by default)
_P3D_OPTIONS = _options(Pascal3DCar, "split", *_UNSPLIT_SET)
DATASETS.add(
    "p3d_car", DatasetSpec(_p3d, 5, "p3d", _P3D_OPTIONS, eval_options={"with_points": True}, by_category=False)
)
DATASETS.add(
    "compcars", DatasetSpec(_unsplit(CompCars), 5, "images", _options(CompCars, *_UNSPLIT_SET), by_category=False)
)
DATASETS.add(
    "lsun",
    DatasetSpec(
        _unsplit(LSUN),
        5,
        "images",
        _options(LSUN, *_UNSPLIT_SET),
        _from_offset,
        by_category=False,
        data_options=("tag", "cleaned", "padding"),
    ),
)
DATASETS.add(
    "folder",
    DatasetSpec(
        _unsplit(ImageFolder),
        5,
        "images",
        _options(ImageFolder, *_UNSPLIT_SET),
        by_category=False,
        data_options=("extensions",),
    ),
)
#: the built-in datasets' names (a plugin may register more: :func:`list_datasets` names them all)
DATASET_NAMES = tuple(DATASETS)
#: the reference's validation subset sizes of the built-in datasets (each entry's :attr:`DatasetSpec.val_size`)
VAL_SIZES = {name: spec.val_size for name, spec in DATASETS.items()}


def register_dataset(name: str, spec: DatasetSpec, *, overwrite: bool = False) -> DatasetSpec:
    """Register a dataset as ``name`` (:meth:`unicorn.registry.Registry.add`); returns ``spec``.

    Raises:
        TypeError: ``spec`` is not a :class:`DatasetSpec` (a bare build function, say).
        ValueError: ``name`` is taken (unless ``overwrite``).
    """
    if not isinstance(spec, DatasetSpec):
        raise TypeError(f"register_dataset({name!r}, spec): spec must be a DatasetSpec(build, ...), got {spec!r}")
    return DATASETS.add(name, spec, overwrite=overwrite)


def list_datasets() -> list[str]:
    """Every registered dataset's name, sorted (the built-in ones and the plugins')."""
    return DATASETS.names()


def dataset_spec(name: str) -> DatasetSpec:
    """The registry entry of a dataset name.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones are listed).
    """
    return DATASETS.get(name)


def build_dataset(
    name: str,
    split: Split,
    root: str | os.PathLike,
    img_size: int = 64,
    categories: str | list[str] | None = None,
    seed: int = 0,
    on_error: OnError = "raise",
    **options: Any,
) -> Dataset:
    """The full dataset of one split (before the validation subset is taken).

    Args:
        name: a registered dataset (:func:`list_datasets`).
        split: ``"train"``, ``"val"`` or ``"test"``; training splits are augmented where the reference does.
        root: dataset root (for ``synthetic``: the generated dataset folder).
        img_size: image side (ShapeNet-NMR images keep their stored size).
        categories: ShapeNet / synthetic categories.
        seed: seed of the fixed evaluation view choice (ShapeNet).
        on_error: ``"raise"`` or ``"skip"`` unreadable images.
        **options: extra constructor arguments of the dataset class (e.g. ``tag`` for LSUN, ``eval_size``): its
            entry's :attr:`DatasetSpec.options`.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones listed).
        unicorn.registry.UnknownOptionError: an option that the dataset does not take (its options listed).
        DatasetError: an unknown split.
    """
    spec = dataset_spec(name)
    check_options(f"dataset {name!r}", options, spec.options)
    if split not in ("train", "val", "test"):
        raise DatasetError(f"split must be 'train', 'val' or 'test', got {split!r}")
    return spec.build(root, split, img_size, categories, seed, on_error, **options)


def val_indices(name: str, n: int, size: int | None = None) -> list[int]:
    """Indices of the validation subset of a split of ``n`` items, as the reference picks them.

    ShapeNet: the first models; CUB: the first after a seed-123 shuffle; LSUN: 5 images from offset 17;
    others: the first images. ``size`` defaults to :data:`VAL_SIZES` and is capped at ``n``.
    """
    spec = dataset_spec(name)
    return spec.val_pick(n, min(spec.val_size if size is None else size, n))


def synthetic_options(
    root: str | os.PathLike | None,
    categories: str | list[str] | None = None,
    synthetic: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The arguments of :func:`~unicorn.data.synthetic.writer.ensure_synthetic_dataset` for a ``synthetic`` dataset.

    Args:
        root: parent folder of generated datasets (None: the cache, ``$UNICORN_CACHE/synthetic``).
        categories: the generated categories (None: :data:`SYNTHETIC_DEFAULTS`).
        synthetic: ``mode``, ``n_models``, ``seed`` and other generator options over :data:`SYNTHETIC_DEFAULTS`.
    """
    category = SYNTHETIC_DEFAULTS["category"] if categories is None else categories
    return {**SYNTHETIC_DEFAULTS, "root": root, "category": category, **dict(synthetic or {})}


def stored_image_size(name: str, synthetic: Mapping[str, Any] | None = None) -> int | None:
    """The side of the images a dataset returns as stored, not resized to ``img_size``: for ``synthetic`` its
    ``image_size`` (the generator's default unless ``synthetic`` gives one); None for the datasets whose loaders
    resize to ``img_size``, and for ShapeNet-NMR (64 px as published, but a synthetic set of another size may be
    read as one)."""
    return dataset_spec(name).stored_size(synthetic)


def dataset_root(
    name: str,
    root: str | os.PathLike | None,
    categories: str | list[str] | None = None,
    synthetic: dict[str, Any] | None = None,
) -> Path:
    """Folder a dataset is read from: ``root``, or for ``synthetic`` the generated dataset's folder under it."""
    return dataset_spec(name).folder(root, categories, synthetic)


def prepare_dataset(
    name: str,
    root: str | os.PathLike | None,
    categories: str | list[str] | None = None,
    synthetic: dict[str, Any] | None = None,
) -> Path:
    """Generate the ``synthetic`` dataset if it is absent (other datasets are read as they are); returns
    :func:`dataset_root`."""
    spec = dataset_spec(name)
    return (spec.prepare or spec.folder)(root, categories, synthetic)


def _check_generation_root(root: str | os.PathLike | None, generate: bool) -> None:
    """Generate the synthetic dataset only where it is meant to go: the cache (``$UNICORN_CACHE``, where a missing
    folder is created), an existing folder, or anywhere with ``synthetic.generate=true``; a misspelt root is an
    error, not tens of MB written to a new folder.

    Raises:
        DatasetNotFoundError: ``root`` does not exist, is outside the cache and generation was not asked for.
    """
    from unicorn.data.synthetic.writer import default_cache_dir

    if root is None or generate:
        return
    path = Path(root).expanduser().resolve()
    cache = default_cache_dir().parent.expanduser().resolve()
    if path.exists() or path.is_relative_to(cache):
        return
    raise DatasetNotFoundError(
        path,
        "synthetic dataset root (dataset.root)",
        f"The synthetic dataset is generated on first use only into the cache ({cache}, $UNICORN_CACHE) or an "
        "existing folder: correct the path, create the folder, or ask for generation there with "
        "dataset.synthetic.generate=true",
    )
