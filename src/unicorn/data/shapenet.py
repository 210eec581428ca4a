"""ShapeNet renderings of Kato et al. (NMR) in DVR's folder form, also the synthetic benchmark's form.

Expected layout (``root`` = ``datasets/shapenet_nmr``, DVR's ``NMR_Dataset``)::

    metadata.yaml                           # {synset: {id: synset, name: "airplane,aeroplane,plane"}, ...}
    <synset>/softras_{train,val,test}.lst   # one model id per line
    <synset>/<model>/image/0000.png ...     # 64x64 RGB on white, one per view (24 for NMR)
    <synset>/<model>/mask/0000.png ...
    <synset>/<model>/cameras.npz            # world_mat_<v>, camera_mat_<v> (4x4, DVR/OpenCV convention)
    <synset>/<model>/pointcloud.npz         # points, normals (P, 3) in the ShapeNet frame, max |coord| 0.5

Poses are converted to unicorn's convention (``x_view = x_world @ R + T``, view +X left, +Y up) and points to
the object frame UNICORN uses, ``(x, y, z) -> (-z, y, x)``; see :func:`dvr_to_unicorn_pose`. Images and masks are
read as stored (EXIF orientation not applied, unlike user photos): the cameras describe the stored pixel grid.
"""

from __future__ import annotations

import re
import zipfile
from collections import Counter
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import yaml

from unicorn.data.common import OnError, UnicornDataset
from unicorn.data.images import (
    DatasetError,
    DatasetNotFoundError,
    ImageLoadError,
    load_image,
    load_mask,
    open_image,
    read_text,
    require,
    to_chw_tensor,
)
from unicorn.metrics.mesh_evaluator import GT_EXTENT, GT_EXTENT_TOLERANCE

__all__ = [
    "SHAPENET_CATEGORIES",
    "ShapeNetNMR",
    "ViewCountError",
    "ViewSizeError",
    "dvr_to_unicorn_points",
    "dvr_to_unicorn_pose",
    "unicorn_to_dvr_points",
    "unicorn_to_dvr_world_mat",
]

#: the 13 NMR categories: UNICORN's config name -> ShapeNet synset
SHAPENET_CATEGORIES = {
    "airplane": "02691156",
    "bench": "02828884",
    "cabinet": "02933112",
    "car": "02958343",
    "chair": "03001627",
    "display": "03211117",
    "lamp": "03636649",
    "speaker": "03691459",
    "rifle": "04090263",
    "sofa": "04256520",
    "table": "04379243",
    "phone": "04401088",
    "vessel": "04530566",
}

# ShapeNet object frame -> UNICORN object frame is x @ _SN_TO_UNI, i.e. (x, y, z) -> (-z, y, x)
_SN_TO_UNI = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
# OpenCV camera axes (x right, y down) -> PyTorch3D / unicorn camera axes (x left, y up)
_CV_TO_UNI_CAM = np.diag([-1.0, -1.0, 1.0])

#: a view's image and mask file name (``0000.png``, ``0001.png``...)
_VIEW_NAME = re.compile(r"\d{4}\.png")
_HINT = (
    "Download DVR's NMR_Dataset.zip (https://s3.eu-central-1.amazonaws.com/avg-projects/"
    "differentiable_volumetric_rendering/data/NMR_Dataset.zip, 33 GB), unzip it and rename NMR_Dataset to "
    "the dataset root. For an offline stand-in, generate the synthetic benchmark: "
    "unicorn-data synth --out DIR."
)


def dvr_to_unicorn_pose(world_mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convert a DVR ``world_mat`` to unicorn's ``(R, T)``.

    DVR maps ShapeNet-frame column vectors to OpenCV camera coordinates, ``p_cam = R_dvr p + t``. With
    ``p = p_uni @ A`` (``A`` the inverse of the point conversion) and the camera-axis flip
    ``C = diag(-1,-1,1)``, ``p_view = p_uni @ (A R_dvr^T C) + t C``. The reference copies ``t`` without
    ``C``, which only holds for cameras aimed at the origin; here the translation is flipped too.

    Args:
        world_mat: (4, 4) or (3, 4) extrinsic matrix.

    Returns:
        R (3, 3) and T (3,) float64 with ``x_view = x_world @ R + T``.
    """
    P = np.asarray(world_mat, dtype=np.float64)
    R_dvr, t_dvr = P[:3, :3], P[:3, 3]
    R = _SN_TO_UNI.T @ R_dvr.T @ _CV_TO_UNI_CAM
    T = t_dvr @ _CV_TO_UNI_CAM
    return R, T


def unicorn_to_dvr_world_mat(R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`dvr_to_unicorn_pose`: unicorn ``R`` (3, 3), ``T`` (3,) to a (4, 4) ``world_mat``."""
    R, T = np.asarray(R, dtype=np.float64), np.asarray(T, dtype=np.float64)
    world_mat = np.eye(4)
    world_mat[:3, :3] = _CV_TO_UNI_CAM @ R.T @ _SN_TO_UNI.T
    world_mat[:3, 3] = T @ _CV_TO_UNI_CAM
    return world_mat


def dvr_to_unicorn_points(points: np.ndarray) -> np.ndarray:
    """ShapeNet / DVR object frame (P, 3) to UNICORN's object frame: ``(x, y, z) -> (-z, y, x)``."""
    return np.asarray(points) @ _SN_TO_UNI


def unicorn_to_dvr_points(points: np.ndarray) -> np.ndarray:
    """Inverse of :func:`dvr_to_unicorn_points`."""
    return np.asarray(points) @ _SN_TO_UNI.T


class ViewSizeError(ImageLoadError):
    """A view image or mask whose size is not the dataset's (:attr:`ShapeNetNMR.view_size`): the items could not
    be batched together, so it is skipped like an unreadable image under ``on_error="skip"``."""

    lead = "wrong size of"


class ViewCountError(ImageLoadError):
    """A model with another number of views than the dataset's (:attr:`ShapeNetNMR.n_views`, its first model's): its
    items would miss views or leave some out, so they are skipped like an unreadable image under
    ``on_error="skip"``."""

    lead = "wrong number of views in"


def _view_images(folder: Path) -> list[Path]:
    """A model's view images in ``folder`` (``0000.png``...), sorted; none if it is missing.

    The views' own names only: not a copy's or a file system's hidden files (macOS's ``._0000.png``).
    """
    return sorted(path for path in folder.glob("*.png") if _VIEW_NAME.fullmatch(path.name))


def _read_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    """Every array of the numpy archive ``path`` (``what`` names it when it is missing).

    Raises:
        DatasetNotFoundError: the file is missing.
        DatasetError: it is not a readable ``.npz`` of plain arrays (corrupt, truncated, pickled objects).
    """
    if not path.exists():
        raise DatasetNotFoundError(path, what, _HINT)
    if not zipfile.is_zipfile(path):  # numpy would try to unpickle it, and say so
        raise DatasetError(f"cannot read {path}: not a numpy .npz archive (a zip file), or truncated")
    try:
        with np.load(path) as archive:  # allow_pickle=False: object arrays are refused, never unpickled
            return {key: archive[key] for key in archive.files}
    except Exception as err:  # bad bytes raise many kinds (ValueError, BadZipFile, EOFError, zlib.error, ...)
        reason = " ".join(str(err).split())
        raise DatasetError(f"cannot read {path} as a numpy .npz archive: {type(err).__name__}: {reason}") from None


def read_metadata(root: Path) -> dict[str, dict[str, str]]:
    """``metadata.yaml`` as ``{synset: {"id": ..., "name": ...}}``.

    Raises:
        DatasetNotFoundError: the file is missing.
        DatasetError: it is not UTF-8 YAML of plain data (no ``!!python/...`` tags) mapping each synset to a
            table, or lists no synset.
    """
    path = require(root / "metadata.yaml", "ShapeNet metadata.yaml", _HINT)
    try:
        # every scalar as its text: an unquoted synset such as 03001627 would be YAML 1.1 octal (787351)
        data = yaml.load(read_text(path), Loader=yaml.BaseLoader)  # noqa: S506 - BaseLoader builds no object
    except yaml.YAMLError as err:
        mark, problem = getattr(err, "problem_mark", None), getattr(err, "problem", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: {problem}" if mark and problem else str(err)
        raise DatasetError(f"cannot read {path} as YAML: {' '.join(where.split())}") from None
    if not isinstance(data, dict) or not data:
        got = f"a {type(data).__name__}" if data else "nothing"
        raise DatasetError(f"{path}: expected a table {{synset: {{id: ..., name: ...}}}}, got {got}")
    for synset, info in data.items():
        if not isinstance(info, dict):
            raise DatasetError(f"{path}: synset {synset!r} maps to a {type(info).__name__}, expected {{id, name}}")
    return {str(k): {"id": str(v.get("id", k)), "name": str(v.get("name", ""))} for k, v in data.items()}


def resolve_categories(metadata: dict[str, dict[str, str]], categories: str | list[str] | None) -> list[str]:
    """Synset ids for category names (any comma-separated token of the metadata name) or ids; None = all.

    Raises:
        DatasetError: an unknown category (a number: a synset unquoted in YAML), or a name that several synsets
            share (a synthetic category generated into a ShapeNet root is named as the ShapeNet one it stands in
            for): the message names the synsets.
    """
    if categories is None:
        return sorted(metadata)
    if isinstance(categories, str):
        categories = [categories]
    by_name: dict[str, list[str]] = {}
    for synset, info in metadata.items():
        for token in dict.fromkeys(token.strip() for token in info["name"].split(",")):
            by_name.setdefault(token, []).append(synset)
    synsets = []
    for cat in categories:
        given_as_number = isinstance(cat, int) and not isinstance(cat, bool)
        cat = str(cat)
        if cat in metadata:
            synsets.append(cat)
        elif len(by_name.get(cat, ())) == 1:
            synsets.append(by_name[cat][0])
        elif cat in by_name:
            named = ", ".join(f"{synset} ({metadata[synset]['name']})" for synset in by_name[cat])
            raise DatasetError(
                f"ShapeNet category {cat!r} names several synsets in metadata.yaml: {named}; give the synset, or a "
                "name only one of them has"
            )
        else:
            known = sorted({*metadata, *by_name})
            # a config file's unquoted synset: YAML reads 03001627 as the octal number 787351
            number = "; a number: write synsets in quotes ('03001627') in YAML files" if given_as_number else ""
            raise DatasetError(f"unknown ShapeNet category {cat!r}{number}; metadata.yaml lists {known}")
    return synsets


class ShapeNetNMR(UnicornDataset):
    """NMR renderings (DVR form) with ground-truth poses, masks and point clouds.

    Args:
        root: dataset root (holds ``metadata.yaml``).
        categories: names (e.g. ``"chair"``, ``"speaker"``) or synset ids; None for every category.
        split: ``"train"``, ``"val"`` or ``"test"`` (SoftRas lists).
        views: ``"all"``: every (model, view) pair is an item, item k = model ``k % n_models``, view
            ``k // n_models`` (the reference's order); ``"random"``: one view per model, drawn once from
            ``seed`` and the model's place in its category's split lists (the reference draws it unseeded): a
            category's views are the same whatever categories are loaded beside it.
        with_points: add ``points``/``normals``; defaults to True except for ``"train"``.
        n_points: keep this many ground-truth points per model, None for all: a fixed subset per model (seeded by
            ``seed`` and the model's place in its category's split lists, as the random views are), drawn uniformly
            without replacement from the stored points, so that an area-uniform cloud (ONet's, the synthetic set's)
            stays one. Only the stored cloud is checked to reach the unit cube's faces: a small subset is a random
            sample of the surface and may miss a thin part's tip, or a whole face of a box.
        include_test: for ``"train"``, also use the val and test models (the reference's option).
        seed: seed of the view choice and the point subsets.
        on_error: ``"raise"`` or ``"skip"`` unreadable images, images or masks of another size than
            :attr:`view_size` (:class:`ViewSizeError`), and the items of a model with another number of views than
            :attr:`n_views` (:class:`ViewCountError`, checked at its first item read).

    A malformed ``metadata.yaml``, split list, ``cameras.npz`` or ``pointcloud.npz`` is a
    :class:`~unicorn.data.images.DatasetError` naming the file, whatever ``on_error``.

    Items: ``image`` (3, H, W), ``mask`` (1, H, W), ``R`` (3, 3), ``T`` (3,) (``has_pose`` True),
    ``category`` (index into :attr:`synsets`), ``model`` (index into :attr:`models`: which object), ``view``,
    optionally ``points``/``normals`` (P, 3) in the object frame of ``R``/``T``.
    """

    def __init__(
        self,
        root: str | Path,
        categories: str | list[str] | None = None,
        split: Literal["train", "val", "test"] = "train",
        views: Literal["all", "random"] = "all",
        with_points: bool | None = None,
        n_points: int | None = None,
        include_test: bool = False,
        seed: int = 0,
        on_error: OnError = "raise",
    ) -> None:
        super().__init__(on_error)
        if split not in ("train", "val", "test"):
            raise DatasetError(f"split must be 'train', 'val' or 'test', got {split!r}")
        if views not in ("all", "random"):
            raise DatasetError(f"views must be 'all' or 'random', got {views!r}")
        if n_points is not None and (
            isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or n_points < 1
        ):
            raise DatasetError(
                f"n_points must be a whole number >= 1 (points kept per model) or None (all), got {n_points!r}"
            )
        self.root = require(root, "ShapeNet-NMR root", _HINT)
        self.metadata = read_metadata(self.root)
        self.synsets = resolve_categories(self.metadata, categories)
        self.split, self.views, self.seed = split, views, int(seed)
        self.with_points = (split != "train") if with_points is None else bool(with_points)
        self.n_points = n_points

        splits = [split] + (["val", "test"] if include_test and split == "train" else [])
        self.models: list[tuple[int, Path]] = []  # (category index, model folder)
        self._rank_in_category: list[int] = []  # a model's place in its category's split lists: its draws' seed
        for c, synset in enumerate(self.synsets):
            names = []
            for s in splits:
                lst = require(self.root / synset / f"softras_{s}.lst", f"ShapeNet split list for {synset}", _HINT)
                names += [line.strip() for line in read_text(lst).splitlines() if line.strip()]
            self.models += [(c, self.root / synset / name) for name in names]
            self._rank_in_category += range(len(names))
        if not self.models:
            raise DatasetError(f"no {split} models for categories {self.synsets} under {self.root}")
        first = self.models[0][1] / "image"
        if not first.is_dir():
            raise DatasetNotFoundError(first, "ShapeNet model image folder", _HINT)
        views = _view_images(first)
        #: views per model: the first model's (every model must have as many, :class:`ViewCountError`)
        self.n_views = len(views)
        if self.n_views == 0:
            raise DatasetNotFoundError(first / "0000.png", "ShapeNet view images", _HINT)
        #: (H, W) of every image and mask: the most common among the first model's views
        self.view_size = self._common_size(views)
        # each category draws its views from the seed alone, so that a category's views do not change with the
        # categories loaded beside it (model k of every category draws the same view)
        counts = Counter(category for category, _ in self.models)
        self.random_views = np.concatenate(
            [
                np.random.default_rng(self.seed).integers(0, self.n_views, size=counts[c])
                for c in range(len(self.synsets))
            ]
        )
        self._world_mats: dict[int, dict[str, np.ndarray]] = {}
        self._view_counts: dict[int, int] = {}

    def _common_size(self, views: list[Path]) -> tuple[int, int]:
        """(H, W) that most of ``views`` have (read from their headers); unreadable ones raise or are passed over
        as ``on_error`` says."""
        sizes: Counter[tuple[int, int]] = Counter()
        for path in views:
            try:
                with open_image(path, path) as img:
                    sizes[img.height, img.width] += 1
            except ImageLoadError:
                if self.on_error == "raise":
                    raise
        if not sizes:
            raise DatasetError(f"no readable view image in {views[0].parent}")
        return sizes.most_common(1)[0][0]

    def __len__(self) -> int:
        return len(self.models) * (self.n_views if self.views == "all" else 1)

    def model_view(self, index: int) -> tuple[int, int]:
        """(model index, view index) of item ``index``."""
        if self.views == "all":
            return index % len(self.models), index // len(self.models)
        return index, int(self.random_views[index])

    def model_dir(self, index: int) -> Path:
        """Folder of the model shown by item ``index``."""
        return self.models[self.model_view(index)[0]][1]

    def load_points(self, model: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Ground-truth ``points`` and ``normals`` (P, 3) float32 of a model, in UNICORN's object frame: the stored
        cloud (checked to reach the unit cube's faces), or ``n_points`` of its points drawn uniformly where it holds
        more (see the class)."""
        path = self.models[model][1] / "pointcloud.npz"
        data = _read_npz(path, "ShapeNet point cloud")
        for key in ("points", "normals"):
            if key not in data:
                raise DatasetError(f"{path}: no {key!r} array (it holds {sorted(data)})")
            arr = data[key]
            if arr.ndim != 2 or arr.shape[1] != 3 or not np.issubdtype(arr.dtype, np.number):
                raise DatasetError(f"{path}: {key} must be a (P, 3) array of numbers, got {arr.shape} {arr.dtype}")
        points, normals = data["points"].astype(np.float64), data["normals"].astype(np.float64)
        if len(points) != len(normals) or not (np.isfinite(points).all() and np.isfinite(normals).all()):
            raise DatasetError(f"{path}: points and normals must be as many and finite")
        extent = float(np.abs(points).max(initial=0.0))
        if abs(extent - GT_EXTENT) > GT_EXTENT_TOLERANCE:  # the metrics compare shapes in the unit cube
            raise DatasetError(
                f"{path}: the points must reach the unit cube's faces (max |coord| {GT_EXTENT} +- "
                f"{GT_EXTENT_TOLERANCE}), got {extent:.4f} over {len(points):,} points: normalised otherwise, or "
                "too few points to reach them"
            )
        if self.n_points is not None and self.n_points < len(points):
            # seeded by the model's place in its category: the same subset whatever other categories are loaded
            rng = np.random.default_rng([self.seed, self._rank_in_category[model]])
            keep = rng.choice(len(points), self.n_points, replace=False)
            points, normals = points[keep], normals[keep]
        points, normals = dvr_to_unicorn_points(points), dvr_to_unicorn_points(normals)
        return torch.from_numpy(points.astype(np.float32)), torch.from_numpy(normals.astype(np.float32))

    def view_pose(self, model: int, view: int) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth (R (3, 3), T (3,)) of one view, in UNICORN's conventions.

        A model's ``cameras.npz`` is read once and its world matrices kept (about 1 KB per model): opening the
        archive for every item took a tenth of the data loading.
        """
        path = self.models[model][1] / "cameras.npz"
        mats = self._world_mats.get(model)
        if mats is None:
            mats = {k: v for k, v in _read_npz(path, "ShapeNet cameras.npz").items() if k.startswith("world_mat_")}
            self._world_mats[model] = mats
        name = f"world_mat_{view}"
        if name not in mats:
            raise DatasetError(f"{path}: no {name} for view {view} (it holds {len(mats)} world matrices)")
        mat = mats[name]
        if mat.shape not in ((3, 4), (4, 4)) or not np.issubdtype(mat.dtype, np.number) or not np.isfinite(mat).all():
            raise DatasetError(f"{path}: {name} must be a finite (4, 4) or (3, 4) matrix, got {mat.shape} {mat.dtype}")
        return dvr_to_unicorn_pose(mat)

    def _check_view_count(self, model: int) -> None:
        """Raise :class:`ViewCountError` if a model has another number of views than :attr:`n_views` (counted once
        per model). A model without view images passes: reading its view names the missing file."""
        folder = self.models[model][1]
        if model not in self._view_counts:
            self._view_counts[model] = len(_view_images(folder / "image"))
        count = self._view_counts[model]
        if count not in (0, self.n_views):
            first = self.models[0][1]
            raise ViewCountError(
                folder, f"{count} views, where every model needs the {self.n_views} of the first, {first}"
            )

    def load(self, index: int) -> dict[str, Any]:
        model, view = self.model_view(index)
        category, folder = self.models[model]
        self._check_view_count(model)
        image_path, mask_path = folder / "image" / f"{view:04d}.png", folder / "mask" / f"{view:04d}.png"
        # the stored pixel grid, EXIF orientation not applied: the cameras were made for it
        image = load_image(image_path, exif_orientation=False)
        mask = load_mask(mask_path, exif_orientation=False)
        for path, arr in ((image_path, image), (mask_path, mask)):
            if arr.shape[:2] != self.view_size:
                (H, W), (h, w) = arr.shape[:2], self.view_size
                raise ViewSizeError(path, f"{H} x {W} pixels (H x W), the dataset's views {h} x {w}")
        R, T = self.view_pose(model, view)
        item: dict[str, Any] = {
            "image": to_chw_tensor(image),
            "mask": to_chw_tensor(mask),
            "R": torch.from_numpy(R.astype(np.float32)),
            "T": torch.from_numpy(T.astype(np.float32)),
            "has_pose": torch.tensor(True),
            "has_mask": torch.tensor(True),
            "category": torch.tensor(category, dtype=torch.int64),
            "model": torch.tensor(model, dtype=torch.int64),
            "view": torch.tensor(view, dtype=torch.int64),
        }
        if self.with_points:
            item["points"], item["normals"] = self.load_points(model)
        return item
