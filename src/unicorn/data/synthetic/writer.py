"""Write the synthetic benchmark in the DVR / NMR layout read by :class:`unicorn.data.shapenet.ShapeNetNMR`.

Per model (``<root>/<synset>/<model>/``): ``image/`` and ``mask/`` PNGs, ``cameras.npz`` (DVR
``world_mat_<v>``, ``camera_mat_<v>`` and their inverses), ``pointcloud.npz`` (``points``, ``normals``
float16, ``loc``, ``scale``) and ``mesh.obj`` in the ShapeNet object frame (as DVR stores them), plus
``views.npz`` (``azim``, ``elev``, ``roll``, ``dist``, ``tx``, ``ty`` per view; the angles in degrees, in UNICORN's
convention, :func:`unicorn.geometry.rotations.azim_elev_roll_to_rotation`: azimuth 0 puts the camera on -Z and 90 on
-X, half a turn from :func:`~unicorn.geometry.rotations.look_at_view_transform`'s) and ``params.json`` (shape and
texture parameters). Per category: ``softras_{train,val,test}.lst``; at the root: ``metadata.yaml`` and
``synthetic.json`` (generator settings).

Everything is a deterministic function of the seed: model ``i`` of a category draws its shape, views and
surface points from ``numpy.random.default_rng([seed, category_index, i, stream])``.
"""

from __future__ import annotations

import contextlib
import fcntl
import inspect
import json
import logging
import math
import os
import shutil
import socket
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
import yaml
from PIL import Image
from tqdm.auto import tqdm

from unicorn.checks import MAX_SEED
from unicorn.data.images import DatasetError, check_image_size
from unicorn.data.shapenet import unicorn_to_dvr_points, unicorn_to_dvr_world_mat
from unicorn.data.synthetic.render import (
    BACKGROUND_KINDS,
    check_background_kinds,
    random_background,
    render_object,
)
from unicorn.data.synthetic.sampling import (
    NMR_FOV,
    WILD_ROLL,
    WILD_SHIFT,
    Mode,
    check_view_ranges,
    model_streams,
    sample_surface_points,
    sample_views,
    split_indices,
    split_sizes,
    views_to_cameras,
)
from unicorn.data.synthetic.shapes import CATEGORIES, ProceduralObject, build_object
from unicorn.errors import UserError, pid_alive
from unicorn.folders import make_parent_folders
from unicorn.metrics.sampling import check_point_count

__all__ = [
    "ANOTHER_ROOT",
    "DescribeDifference",
    "GENERATOR_VERSION",
    "RECORDED_OPTIONS",
    "StaleSyntheticDataset",
    "SyntheticOutputExistsError",
    "check_generation_counts",
    "check_generation_sizes",
    "check_manifest",
    "check_output_folder",
    "check_synthetic_settings",
    "default_cache_dir",
    "ensure_synthetic_dataset",
    "generate_synthetic_dataset",
    "generation_lock",
    "generation_settings",
    "setting_difference",
    "synthetic_dataset_path",
]

log = logging.getLogger(__name__)

#: bump when the output changes: it is part of the cache folder's name and of ``synthetic.json``, so that a
#: dataset of an older generator is never reused (2: every category has a front, wider instance variation)
GENERATOR_VERSION = 2

#: the options of :func:`generate_synthetic_dataset` that ``synthetic.json`` records (beside the categories, mode,
#: model count and seed), as they were given: a dataset made before an option existed then matches its default
RECORDED_OPTIONS = (
    "image_size",
    "n_views",
    "supersample",
    "n_points",
    "backgrounds",
    "background_kinds",
    "roll",
    "shift",
)


def _write_model(
    folder: Path,
    obj: ProceduralObject,
    views: dict[str, np.ndarray],
    image_size: int,
    supersample: int,
    n_points: int,
    rng_bg: np.random.Generator,
    rng_points: np.random.Generator,
    background_kinds: Sequence[str] | None,
) -> None:
    """Write one model's views, masks, cameras, points and mesh; ``background_kinds``: the kinds of random
    background to draw from, or None for white."""
    R, T = views_to_cameras(views)
    V = len(R)
    backgrounds = None
    if background_kinds is not None:
        backgrounds = np.stack([random_background(rng_bg, image_size, background_kinds) for _ in range(V)])
    images, coverage = render_object(
        obj, R, T, image_size=image_size, fov=NMR_FOV, supersample=supersample, backgrounds=backgrounds
    )
    (folder / "image").mkdir(parents=True)
    (folder / "mask").mkdir()
    for v in range(V):
        Image.fromarray(np.round(images[v] * 255).astype(np.uint8), "RGB").save(folder / "image" / f"{v:04d}.png")
        Image.fromarray(((coverage[v] >= 0.5) * 255).astype(np.uint8), "L").save(folder / "mask" / f"{v:04d}.png")

    focal = 1.0 / math.tan(math.radians(NMR_FOV) / 2)
    camera_mat = np.diag([focal, focal, 1.0, 1.0])
    cameras = {}
    for v in range(V):
        world_mat = unicorn_to_dvr_world_mat(R[v], T[v])
        cameras[f"world_mat_{v}"] = world_mat
        cameras[f"world_mat_inv_{v}"] = np.linalg.inv(world_mat)
        cameras[f"camera_mat_{v}"] = camera_mat
        cameras[f"camera_mat_inv_{v}"] = np.linalg.inv(camera_mat)
    np.savez(folder / "cameras.npz", **{k: v.astype(np.float32) for k, v in cameras.items()})

    points, normals = sample_surface_points(obj, n_points, rng_points)
    np.savez(
        folder / "pointcloud.npz",
        points=unicorn_to_dvr_points(points).astype(np.float16),
        normals=unicorn_to_dvr_points(normals).astype(np.float16),
        loc=np.zeros(3, dtype=np.float32),
        scale=np.float32(1.0),
    )
    mesh = obj.mesh()
    mesh = trimesh.Trimesh(unicorn_to_dvr_points(mesh.vertices), mesh.faces, process=False)
    mesh.export(folder / "mesh.obj")
    np.savez(folder / "views.npz", **{k: v.astype(np.float32) for k, v in views.items()})
    (folder / "params.json").write_text(json.dumps(obj.params, indent=1), encoding="utf-8")


def check_generation_sizes(
    image_size: int,
    supersample: int,
    n_points: int,
    names: tuple[str, str, str] = ("image_size", "supersample", "n_points"),
) -> None:
    """Refuse sizes whose arrays would exceed the limits, before anything is written: a view is rendered at
    ``image_size * supersample`` pixels a side (bounded like an image: :func:`unicorn.data.images.check_image_size`),
    and ``n_points`` ground-truth points are sampled per model (:data:`unicorn.metrics.MAX_POINTS`). ``names``:
    what the three settings are called in the message (the options of ``unicorn-data synth``).

    Raises:
        unicorn.checks.SizeLimitError: the message names the setting and the limit.
    """
    side = image_size * supersample
    setting = f"{names[0]} {image_size} with {names[1]} {supersample}"
    check_image_size(setting, "a view rendered supersampled", side, channels=3)
    check_point_count(f"{names[2]} {n_points}", n_points)


#: how a message names a setting that differs, ``(key, recorded value, asked value) -> text``: ``key=value (asked:
#: value)`` by default (:func:`setting_difference`); ``unicorn-data synth`` names its options
DescribeDifference = Callable[[str, Any, Any], str]


def setting_difference(key: str, recorded: Any, asked: Any) -> str:
    """``key=recorded (asked: asked)``: a setting of a generated dataset that differs from the one asked for."""
    return f"{key}={recorded!r} (asked: {asked!r})"


#: the settings :func:`check_generation_sizes` bounds
_SIZE_KEYS = ("image_size", "supersample", "n_points")
#: the most models per category a generation makes (ShapeNet's largest category, tables, has 8,436)
MAX_MODELS = 100_000
#: the most views per model a generation renders (the NMR views: 24)
MAX_VIEWS = 10_000


def check_generation_counts(n_models: int, n_views: int, names: tuple[str, str] = ("n_models", "n_views")) -> None:
    """Refuse fewer than 3 models per category (one per split, :func:`~unicorn.data.synthetic.sampling.split_sizes`),
    more than :data:`MAX_MODELS`, or more than :data:`MAX_VIEWS` views per model, before anything is generated.
    ``names``: what the two settings are called in the message.

    Raises:
        DatasetError: the message names the setting and its limit.
    """
    if n_models < 3:
        raise DatasetError(f"{names[0]} must be at least 3 (one model per split: train, val, test), got {n_models}")
    for name, value, top in zip(names, (n_models, n_views), (MAX_MODELS, MAX_VIEWS), strict=True):
        if value > top:
            raise DatasetError(f"{name} must be at most {top:,}, got {value:,}")


def check_synthetic_settings(categories: str | Sequence[str] | None, settings: Mapping[str, Any]) -> None:
    """Check a configuration's generation settings (``dataset.synthetic``: ``mode``, ``n_models``, ``seed``,
    ``generate`` and :data:`RECORDED_OPTIONS`) and its categories before anything is generated.

    Raises:
        DatasetError: an unknown key or category, or a value out of its range (the message names the key).
    """
    known = ("mode", "n_models", "seed", "generate", *RECORDED_OPTIONS)
    unknown = sorted(set(settings) - set(known))
    if unknown:
        raise DatasetError(f"unknown setting {unknown[0]!r}; the settings are {list(known)}")
    _category_list("chair" if categories is None else categories)

    def whole(key: str, low: int, high: float = math.inf) -> int | None:
        value = settings.get(key)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            top = "" if high == math.inf else f" and <= {high:,}"
            raise DatasetError(f"{key} must be a whole number >= {low}{top}, got {value!r}")
        return value

    n_models = whole("n_models", 3, MAX_MODELS)
    if n_models is not None:
        split_sizes(n_models)
    whole("seed", 0, MAX_SEED)
    whole("n_views", 1, MAX_VIEWS)
    for key in ("image_size", "supersample", "n_points"):
        whole(key, 1)
    sizes = {k: _RECORDED_DEFAULTS[k] if settings.get(k) is None else settings[k] for k in _SIZE_KEYS}
    check_generation_sizes(**sizes)
    mode = settings.get("mode", "nmr")
    check_view_ranges(mode, settings.get("roll"), settings.get("shift"))
    backgrounds = settings.get("backgrounds")
    if backgrounds is not None and not isinstance(backgrounds, bool):
        raise DatasetError(f"backgrounds must be true, false or null (the mode's), got {backgrounds!r}")
    _background_kinds(settings.get("background_kinds"), _random_backgrounds(mode, backgrounds))
    if not isinstance(settings.get("generate", False), bool):
        raise DatasetError(f"generate must be true or false, got {settings['generate']!r}")


def generate_synthetic_dataset(
    out: str | os.PathLike,
    categories: str | Sequence[str] = "chair",
    mode: Mode = "nmr",
    n_models: int = 200,
    seed: int = 0,
    image_size: int = 64,
    n_views: int = 24,
    supersample: int = 3,
    n_points: int = 20000,
    backgrounds: bool | None = None,
    background_kinds: Sequence[str] | None = None,
    roll: float | None = None,
    shift: float | None = None,
    progress: bool = True,
) -> Path:
    """Generate the synthetic benchmark into ``out`` (created; existing model folders are an error).

    Args:
        out: dataset root to write.
        categories: one or more names from :data:`~unicorn.data.synthetic.shapes.CATEGORIES`.
        mode: ``"nmr"`` (ShapeNet-NMR stand-in) or ``"wild"`` (random views and backgrounds).
        n_models: models per category, split 70 / 10 / 20 % into train / val / test.
        seed: everything is a deterministic function of it.
        image_size: side of the images.
        n_views: views per model (24 for NMR).
        supersample: rays per pixel along each axis.
        n_points: ground-truth surface points per model.
        backgrounds: random backgrounds (solid, gradient, checker, noise) behind the object, or white; None: the
            mode's (``wild`` random, ``nmr`` white). The other choice separates the viewpoints from the
            backgrounds in a control run.
        background_kinds: the kinds of random background drawn from (some of
            :data:`~unicorn.data.synthetic.render.BACKGROUND_KINDS`: ``solid``, ``gradient``, ``checker``,
            ``noise``); None: all four. Only with random backgrounds.
        roll: the wild mode's largest roll in degrees (None: 15); 0 keeps every view upright.
        shift: the wild mode's largest off-centre shift along x and y in view units (None: 0.1); 0 centres every
            view. Either leaves the other angles and distances of every view as they are, so that a dataset with
            ``roll=0, shift=0`` is the default one's views, upright and centred: a control for what roll and
            shifts cost.
        progress: show a progress bar.

    Returns:
        ``out`` as a Path.
    """
    options = {name: value for name, value in locals().items() if name in RECORDED_OPTIONS}  # the arguments as given
    out = Path(out)
    categories = _category_list(categories)
    split_sizes(n_models)  # refuses too few models before anything is written
    check_generation_sizes(image_size, supersample, n_points)
    check_view_ranges(mode, roll, shift)
    kinds = _background_kinds(background_kinds, _random_backgrounds(mode, backgrounds))
    metadata = check_output_folder(out, categories)  # before anything is written
    settings = _joined_settings(out, generation_settings(categories, mode, n_models, seed, **options))
    out.mkdir(parents=True, exist_ok=True)

    bar = tqdm(total=n_models * len(categories), desc=f"synthetic {mode}", unit="model", disable=not progress)
    for cat in categories:
        synset, _ = CATEGORIES[cat]
        cat_dir = out / synset
        names = [f"{cat}_{seed}_{i:05d}" for i in range(n_models)]
        for i, name in enumerate(names):
            streams = model_streams(seed, cat, i)
            obj = build_object(cat, streams[0])
            obj.params.update(category=cat, seed=seed, index=i)
            views = sample_views(mode, n_views, streams[1], roll, shift)
            _write_model(cat_dir / name, obj, views, image_size, supersample, n_points, *streams[2:], kinds)
            bar.update()
        for split, idx in split_indices(seed, cat, n_models).items():
            (cat_dir / f"softras_{split}.lst").write_text(
                "".join(f"{names[i]}\n" for i in sorted(idx)), encoding="utf-8"
            )
        metadata[synset] = {"id": synset, "name": f"{cat},synthetic_{cat}"}
    bar.close()
    _write_metadata(out / "metadata.yaml", metadata)
    (out / "synthetic.json").write_text(json.dumps(settings, indent=1), encoding="utf-8")
    return out


#: the defaults of :data:`RECORDED_OPTIONS`, from the signature itself
_RECORDED_DEFAULTS = {
    name: param.default
    for name, param in inspect.signature(generate_synthetic_dataset).parameters.items()
    if name in RECORDED_OPTIONS
}


def _category_list(categories: str | Sequence[str]) -> list[str]:
    """``categories`` as a list, each one of :data:`~unicorn.data.synthetic.shapes.CATEGORIES`.

    Raises:
        DatasetError: no category, an unknown one (the message lists them) or one named twice (a category is
            generated once: its models would be written twice into the same folders).
    """
    categories = [categories] if isinstance(categories, str) else list(categories)
    if not categories:
        raise DatasetError(f"no synthetic category given; choose from {sorted(CATEGORIES)}")
    for i, cat in enumerate(categories):
        if cat not in CATEGORIES:
            raise DatasetError(f"unknown synthetic category {cat!r}; choose from {sorted(CATEGORIES)}")
        if cat in categories[:i]:
            raise DatasetError(f"synthetic category {cat!r} is named twice in {categories}; name each category once")
    return categories


def _random_backgrounds(mode: str | None, backgrounds: object) -> bool:
    """Whether the views are drawn over random backgrounds: ``backgrounds`` as given, None: the mode's (wild)."""
    return mode == "wild" if backgrounds is None else bool(backgrounds)


def _background_kinds(kinds: Sequence[str] | None, random_backgrounds: bool) -> tuple[str, ...] | None:
    """The kinds of random background to draw from (all of them for None), or None for white backgrounds.

    Raises:
        DatasetError: unknown or no kinds, or kinds asked for with white backgrounds.
    """
    if kinds is None:
        return BACKGROUND_KINDS if random_backgrounds else None
    kinds = check_background_kinds(kinds)
    if not random_backgrounds:
        raise DatasetError(f"background_kinds {list(kinds)} asks for random backgrounds, but they are white")
    return kinds


class SyntheticOutputExistsError(DatasetError, FileExistsError):
    """The output folder already holds models of a category to generate."""


def check_output_folder(
    out: str | os.PathLike,
    categories: str | Sequence[str],
    settings: dict[str, Any] | None = None,
    describe: DescribeDifference = setting_difference,
) -> dict[str, dict]:
    """Refuse an output folder that :func:`generate_synthetic_dataset` cannot write into: one that holds
    something other than a dataset (a ``metadata.yaml`` that is not a category table) or already holds one of
    these categories (its model lists would be replaced). Other categories may share the folder, when its dataset
    was generated with ``settings`` (:func:`generation_settings`; None: not checked); ``describe`` words a setting
    that differs in the message.

    Returns:
        The folder's category table (its ``metadata.yaml``; {} for none).

    Raises:
        DatasetError: an unknown or repeated category, or the folder holds something else.
        SyntheticOutputExistsError: names the first category in the way.
    """
    out = Path(out)
    categories = _category_list(categories)
    metadata = _read_metadata(out / "metadata.yaml")
    for cat in categories:
        folder = out / CATEGORIES[cat][0]
        if folder.exists():
            raise SyntheticOutputExistsError(
                f"{out} already holds {cat} models ({folder}): use that dataset as it is, delete it, or generate "
                "into another folder"
            )
    if settings is not None:
        _joined_settings(out, settings, describe)
    return metadata


def _joined_settings(
    out: Path, settings: dict[str, Any], describe: DescribeDifference = setting_difference
) -> dict[str, Any]:
    """``settings`` of a generation into ``out``, with the categories already there when ``out`` holds a generated
    dataset (its ``synthetic.json``): other categories join one only with the same settings, which the file then
    describes for all of them.

    Raises:
        SyntheticOutputExistsError: the folder's dataset was generated with other settings (the message names one).
    """
    path = out / "synthetic.json"
    if not path.is_file():
        return settings
    try:
        earlier = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:
        earlier = None
    if not isinstance(earlier, dict):
        raise DatasetError(f"{path} is not a generated dataset's synthetic.json; generate into another folder")
    was, asked = _in_effect(earlier), _in_effect(settings)
    other = [k for k in settings if k != "categories" and was.get(k) != asked[k]]
    if other:
        key = other[0]
        raise SyntheticOutputExistsError(
            f"{out} holds a synthetic dataset generated with {describe(key, earlier.get(key), settings[key])}; "
            "other categories join it only with the same settings: generate into another folder"
        )
    return {**settings, "categories": [*earlier.get("categories", []), *settings["categories"]]}


def _read_metadata(path: Path) -> dict[str, dict]:
    """The category table of an existing ``metadata.yaml`` (ShapeNet-NMR's: synset -> ``{id, name}``), else {}.

    Raises:
        DatasetError: the file is not such a table (the folder holds something else).
    """
    if not path.exists():
        return {}
    try:
        # every scalar as its text: an unquoted synset such as 03001627 would be YAML 1.1 octal (787351)
        metadata = yaml.load(path.read_text(encoding="utf-8"), Loader=yaml.BaseLoader) or {}  # noqa: S506 - builds no object
    except (yaml.YAMLError, UnicodeDecodeError, OSError):
        metadata = None  # not YAML, not text
    if not isinstance(metadata, dict) or not all(isinstance(v, dict) and "id" in v for v in metadata.values()):
        raise DatasetError(
            f"{path} is not a dataset's metadata.yaml (a table synset: {{id, name}}): the folder holds something "
            "else; generate into another folder"
        )
    return metadata


def _write_metadata(path: Path, metadata: dict[str, dict]) -> None:
    """Write ``metadata`` (:func:`_read_metadata`'s table with the generated categories added) to ``path``.

    A file already there (a ShapeNet-NMR root's, or an earlier generation's) keeps its bytes: the new entries are
    appended to it where the result reads back as ``metadata``, else the table is written anew (a flow-style file).
    The file is replaced in one rename, so an interrupted generation leaves the earlier one.
    """
    old = path.read_text(encoding="utf-8") if path.is_file() else ""
    earlier = (yaml.load(old, Loader=yaml.BaseLoader) or {}) if old else {}  # noqa: S506 - builds no object
    added = {synset: info for synset, info in metadata.items() if synset not in earlier}
    text = yaml.safe_dump(metadata, sort_keys=True)
    if old and isinstance(earlier, dict):
        appended = old + ("" if old.endswith("\n") else "\n") + yaml.safe_dump(added, sort_keys=True)
        try:
            same = yaml.load(appended, Loader=yaml.BaseLoader) == metadata  # noqa: S506 - builds no object
        except yaml.YAMLError:
            same = False
        text = appended if same else text
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # a write that failed (a full disk) leaves no temporary file


class StaleSyntheticDataset(UserError, ValueError):
    """A generated dataset's ``synthetic.json`` does not match the settings (or the generator) asked for."""


#: how a message about a dataset folder that cannot be used says to generate the dataset elsewhere, by default: the
#: ``root`` of :func:`ensure_synthetic_dataset`, which a training run sets; ``unicorn-data synth`` names ``--out``
ANOTHER_ROOT = "generate it under another root (dataset.root=DIR in a training run)"


def check_manifest(
    root: str | os.PathLike,
    *,
    describe: DescribeDifference = setting_difference,
    elsewhere: str = ANOTHER_ROOT,
    **expected: object,
) -> dict[str, object]:
    """Check a generated dataset's ``synthetic.json`` against the current generator and ``expected`` settings.

    Args:
        root: the generated dataset.
        describe: how the message words each setting that differs.
        elsewhere: how the message says to generate the dataset in another folder (:data:`ANOTHER_ROOT`).
        **expected: settings it must have been generated with (``categories``, ``mode``, ``image_size``...);
            the generator version is always checked. An option left to the mode (None) and the mode's own value
            written out are the same setting.

    Returns:
        The recorded settings.

    Raises:
        StaleSyntheticDataset: the generator version or a setting differs (the message names it), or the file
            is damaged.
    """
    root = Path(root)
    path = root / "synthetic.json"
    try:
        settings = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as err:  # cut short or not JSON: the generation did not write it
        settings, problem = None, f": {err}"
    else:
        problem = f": a JSON {type(settings).__name__}" if not isinstance(settings, dict) else ""
    if not isinstance(settings, dict):
        raise StaleSyntheticDataset(
            f"{path} is damaged (not a generated dataset's settings{problem}); delete {root} to generate it again, "
            f"or {elsewhere}"
        )
    expected = _as_recorded({"generator_version": GENERATOR_VERSION, **expected})
    if isinstance(expected.get("categories"), str):
        expected["categories"] = [expected["categories"]]
    was, asked = _in_effect(settings), _in_effect({**settings, **expected})
    # a setting given alike that differs in effect (background_kinds None: white in nmr, all four kinds in wild)
    # differs through the mode or backgrounds, which are named
    wrong = [
        describe(key, settings.get(key), value)
        for key, value in expected.items()
        if (
            sorted(settings.get(key) or []) != sorted(value)
            if key == "categories"
            else was.get(key) != asked[key] and settings.get(key) != value
        )
    ]
    if wrong:
        raise StaleSyntheticDataset(
            f"the synthetic dataset in {root} was generated with {', '.join(wrong)}; delete that folder to "
            f"generate it again, or {elsewhere}"
        )
    return settings


def generation_settings(
    categories: str | Sequence[str], mode: Mode, n_models: int, seed: int, **options: object
) -> dict[str, object]:
    """The settings that :func:`generate_synthetic_dataset` called with these arguments records in
    ``synthetic.json`` (the options left out: its defaults; the generator version and the field of view too), as
    JSON reads them back (tuples as lists), which is how :func:`check_manifest` compares them.

    Raises:
        TypeError: an option that is not one of :data:`RECORDED_OPTIONS`.
    """
    unknown = sorted(set(options) - set(RECORDED_OPTIONS))
    if unknown:
        raise TypeError(f"generation_settings() got options it does not record: {', '.join(unknown)}")
    categories = [categories] if isinstance(categories, str) else list(categories)
    recorded = {
        "generator_version": GENERATOR_VERSION,
        "categories": categories,
        "mode": mode,
        "n_models": n_models,
        "seed": seed,
        **_RECORDED_DEFAULTS,
        **options,
        "fov": NMR_FOV,
    }
    if recorded["background_kinds"] is not None:  # one kind may be given as a string
        recorded["background_kinds"] = check_background_kinds(recorded["background_kinds"])
    return _as_recorded(recorded)


def _as_recorded(value: Any) -> Any:
    """``value`` as ``synthetic.json`` holds it (tuples become lists, numpy scalars numbers)."""
    return json.loads(json.dumps(value, default=_plain))


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"a synthetic dataset setting must be a number, string, list or None, got {value!r}")


def _in_effect(settings: dict[str, Any]) -> dict[str, Any]:
    """``settings`` with the options left to the mode (None) replaced by what the generator then draws, so that
    a dataset made with the mode's own values written out (``backgrounds=True`` in the wild mode, all four kinds,
    ``roll=15``) is the one made with None, and the other way round."""
    settings = dict(settings)
    wild = settings.get("mode") == "wild"
    random_bg = _random_backgrounds(settings.get("mode"), settings.get("backgrounds"))
    kinds = settings.get("background_kinds")
    settings["backgrounds"] = random_bg
    settings["background_kinds"] = (list(BACKGROUND_KINDS) if kinds is None else list(kinds)) if random_bg else None
    if wild:
        for key, default in (("roll", WILD_ROLL), ("shift", WILD_SHIFT)):
            settings[key] = default if settings.get(key) is None else float(settings[key])
    return settings


def default_cache_dir() -> Path:
    """``$UNICORN_CACHE/synthetic`` if the variable is set, else ``~/.cache/unicorn/synthetic``."""
    base = os.environ.get("UNICORN_CACHE")
    return (Path(base).expanduser() if base else Path.home() / ".cache" / "unicorn") / "synthetic"


def synthetic_dataset_path(
    category: str | Sequence[str], mode: Mode, n_models: int, seed: int, root: str | os.PathLike | None = None
) -> Path:
    """Folder that :func:`ensure_synthetic_dataset` uses for these settings (under ``root`` or the cache)."""
    cats = "+".join([category] if isinstance(category, str) else sorted(category))
    base = Path(root).expanduser() if root is not None else default_cache_dir()
    return base / f"{mode}_{cats}_n{n_models}_s{seed}_v{GENERATOR_VERSION}"


def _generation_prefix(final: Path) -> str:
    """The start of the names of the temporary folders in which ``final`` is generated
    (``.<name>.tmp-<host>-<pid>-<token>``)."""
    return f".{final.name}.tmp-"


@contextlib.contextmanager
def generation_lock(folder: str | os.PathLike) -> Iterator[None]:
    """Hold ``.<name>.lock`` beside ``folder`` (an exclusive ``flock``) while a dataset is checked, generated and moved
    into ``folder``: another process generating into the same folder (a sweep's jobs, ``unicorn-data synth --out``
    beside ``unicorn-train``) waits, then finds what this one wrote. Processes of one machine (containers on it
    too); a cache shared over the network between machines is not locked across them. The lock file is removed when
    the block ends.

    Raises:
        NotADirectoryError: a file stands where a folder above ``folder`` goes (the message names it).
    """
    folder = Path(folder)
    make_parent_folders(folder)
    path = folder.parent / f".{folder.name}.lock"
    while True:
        handle = open(path, "a", encoding="utf-8")  # noqa: SIM115 - held open with its lock until the block ends
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("waiting for another process generating %s", folder)
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:  # the holder before removes the file when it is done: hold the lock of the file at the path now
            if os.path.samestat(os.fstat(handle.fileno()), os.stat(path)):
                break
        except FileNotFoundError:
            pass
        handle.close()
    try:
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # nothing left beside the folder; a process waiting on it opens the path again
        handle.close()


def _remove_stale_generations(final: Path) -> None:
    """Delete the temporary folders of generations of ``final`` that a process of this machine, now gone, left (a
    SIGKILL while generating); another machine's (a cache shared over the network) are left alone."""
    host = socket.gethostname()
    for tmp in final.parent.glob(f"{_generation_prefix(final)}*"):
        owner, _, pid = tmp.name[len(_generation_prefix(final)) :].rpartition("-")[0].rpartition("-")
        if owner == host and pid.isdigit() and not pid_alive(int(pid)):
            log.info("removing %s, left by a generation that was killed", tmp)
            shutil.rmtree(tmp, ignore_errors=True)


def ensure_synthetic_dataset(
    root: str | os.PathLike | None = None,
    category: str | Sequence[str] = "chair",
    mode: Mode = "nmr",
    n_models: int = 200,
    seed: int = 0,
    progress: bool = True,
    elsewhere: str = ANOTHER_ROOT,
    **kwargs,
) -> Path:
    """Return the synthetic dataset for these settings, generating it first if it is absent.

    An existing dataset is checked against these settings and the generator version (:func:`check_manifest`),
    so that one made by another generator or with other options is never reused silently.

    Generation writes to a temporary sibling folder that is renamed into place at the end, so an
    interrupted run never leaves a folder that looks complete; a second process asking for the same dataset
    meanwhile waits for it (:func:`generation_lock`) and then reuses it.

    Args:
        root: parent folder of the datasets; defaults to :func:`default_cache_dir` (``$UNICORN_CACHE``).
        category, mode, n_models, seed: see :func:`generate_synthetic_dataset`.
        progress: show a progress bar while generating.
        elsewhere: how an error about the folder says to generate the dataset in another one (:data:`ANOTHER_ROOT`).
        **kwargs: further :func:`generate_synthetic_dataset` options (``image_size``, ``n_views``...); they
            are not part of the folder name: a dataset in the folder generated with other values is an error
            (:class:`StaleSyntheticDataset`), so give each combination its own ``root``.

    Returns:
        The dataset root, ready for :class:`~unicorn.data.shapenet.ShapeNetNMR`.
    """
    _category_list(category)  # before a folder is named after them, or a lock taken
    final = synthetic_dataset_path(category, mode, n_models, seed, root)
    expected = generation_settings(category, mode, n_models, seed, **kwargs)
    if (final / "synthetic.json").exists():
        check_manifest(final, elsewhere=elsewhere, **expected)
        return final
    with generation_lock(final):  # a second process waits here, then finds the first's dataset
        if (final / "synthetic.json").exists():
            check_manifest(final, elsewhere=elsewhere, **expected)
            return final
        if final.is_dir() and any(final.iterdir()):
            raise StaleSyntheticDataset(
                f"{final} holds files but no synthetic.json: it is not a generated dataset; move it away, or "
                f"{elsewhere}"
            )
        _remove_stale_generations(final)
        tmp = final.parent / f"{_generation_prefix(final)}{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            generate_synthetic_dataset(tmp, category, mode, n_models, seed, progress=progress, **kwargs)
            os.replace(tmp, final)  # an empty folder there is replaced
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    return final
