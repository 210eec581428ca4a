"""The random draws of one synthetic model, each a deterministic function of the seed: its views and their
cameras, its surface points, its random streams, and the split it falls in."""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import trimesh

from unicorn.data.images import DatasetError
from unicorn.data.synthetic.shapes import CATEGORIES, ProceduralObject
from unicorn.errors import import_open3d
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.metrics.mesh_evaluator import GT_EXTENT_TOLERANCE

__all__ = [
    "NMR_DISTANCE",
    "NMR_ELEVATION",
    "NMR_FOV",
    "WILD_ROLL",
    "WILD_SHIFT",
    "Mode",
    "model_streams",
    "sample_surface_points",
    "sample_views",
    "check_view_ranges",
    "split_indices",
    "split_sizes",
    "views_to_cameras",
]

#: the NMR renderings' camera: distance, elevation (degrees) and field of view (degrees)
NMR_DISTANCE, NMR_ELEVATION, NMR_FOV = 2.732, 30.0, 30.0

#: the wild mode's default largest roll (degrees) and off-centre shift (view units, each of x and y)
WILD_ROLL, WILD_SHIFT = 15.0, 0.1

Mode = Literal["nmr", "wild"]


def sample_views(
    mode: Mode, n_views: int, rng: np.random.Generator, roll: float | None = None, shift: float | None = None
) -> dict[str, np.ndarray]:
    """Camera parameters of one model's views.

    ``nmr``: azimuth ``360 k / n_views``, elevation 30, no roll, distance 2.732, centred. ``wild``: azimuth
    U[0, 360), elevation U[-10, 30], roll U[-roll, roll], distance 2.732 * U[0.9, 1.1] and an off-centre shift
    (``tx``, ``ty``) U[-shift, shift] in view units. ``roll`` and ``shift`` (wild only; None: :data:`WILD_ROLL`,
    :data:`WILD_SHIFT`) change only those draws: every other angle and distance stays the same.

    Returns:
        dict of (n_views,) float64 arrays ``azim``, ``elev``, ``roll`` (degrees), ``dist``, ``tx``, ``ty``.

    Raises:
        DatasetError: an unknown mode, a negative range, or a range given for the ``nmr`` mode.
    """
    check_view_ranges(mode, roll, shift)
    zeros = np.zeros(n_views)
    if mode == "nmr":
        return {
            "azim": 360.0 * np.arange(n_views) / n_views,
            "elev": zeros + NMR_ELEVATION,
            "roll": zeros,
            "dist": zeros + NMR_DISTANCE,
            "tx": zeros,
            "ty": zeros,
        }
    roll = WILD_ROLL if roll is None else float(roll)
    shift = WILD_SHIFT if shift is None else float(shift)
    return {
        "azim": rng.uniform(0, 360, n_views),
        "elev": rng.uniform(-10, 30, n_views),
        "roll": rng.uniform(-roll, roll, n_views),
        "dist": NMR_DISTANCE * rng.uniform(0.9, 1.1, n_views),
        "tx": rng.uniform(-shift, shift, n_views),
        "ty": rng.uniform(-shift, shift, n_views),
    }


def check_view_ranges(
    mode: str,
    roll: float | None = None,
    shift: float | None = None,
    names: tuple[str, str] = ("roll", "shift"),
) -> None:
    """Refuse an unknown mode and view ranges it cannot take: ``roll`` in [0, 180] degrees and ``shift`` in
    [0, 1] view units, for the ``wild`` mode only (None: the mode's own). ``names``: what ``roll`` and ``shift``
    are called in the message (the options of ``unicorn-data synth``).

    Raises:
        DatasetError: the message names the setting.
    """
    if mode not in ("nmr", "wild"):
        raise DatasetError(f"mode must be 'nmr' or 'wild', got {mode!r}")
    for name, value, top in zip(names, (roll, shift), (180.0, 1.0), strict=True):
        if value is None:
            continue
        if mode == "nmr":
            raise DatasetError(f"{name}={value!r} is for the wild mode; the nmr mode's views have none")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= top:
            raise DatasetError(f"{name} must be a number in [0, {top:g}], got {value!r}")


def views_to_cameras(views: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """UNICORN's pose parametrisation: ``R = Az @ El @ Ro`` and ``T = (tx, ty, dist)``; (V, 3, 3), (V, 3)."""
    R = azim_elev_roll_to_rotation(
        torch.as_tensor(views["azim"], dtype=torch.float64),
        torch.as_tensor(views["elev"], dtype=torch.float64),
        torch.as_tensor(views["roll"], dtype=torch.float64),
    ).numpy()
    T = np.stack([views["tx"], views["ty"], views["dist"]], axis=1)
    return R, T


def sample_surface_points(
    obj: ProceduralObject, n_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface samples of an object, without the surface buried inside other parts.

    Parts are unions of watertight primitives that may interpenetrate; samples lying inside another primitive
    (e.g. the top of a leg inside a seat) are dropped so the point cloud is the visible outer surface, like
    ONet's samples of watertight ShapeNet meshes.

    The cloud reaches the object's farthest vertex (``max |coord|``, 0.5 for a normalised object) within half of
    :data:`~unicorn.metrics.mesh_evaluator.GT_EXTENT_TOLERANCE`, as the evaluation requires of a ground truth: where
    the samples fall short (a few hundred points may all miss a wing tip), the sample nearest that vertex is moved
    onto it, with the normal of its face that faces outwards most.

    Returns:
        points (n_points, 3) and unit face normals (n_points, 3), float64, in the object frame.
    """
    o3d = import_open3d()  # here: reading a generated dataset needs no open3d

    components = [c for part in obj.parts for c in part.mesh.split(only_watertight=False)]
    mesh = trimesh.util.concatenate(components)
    face_comp = np.concatenate([np.full(len(c.faces), i) for i, c in enumerate(components)])
    points, faces = trimesh.sample.sample_surface(mesh, int(n_points * 1.5) + 64, seed=rng)
    comp = face_comp[faces]
    keep = np.ones(len(points), dtype=bool)
    for i, c in enumerate(components):
        if not c.is_watertight:  # an open surface has no inside
            continue
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(c.vertices.astype(np.float32)), o3d.core.Tensor(c.faces.astype(np.uint32)))
        others = comp != i
        occupied = scene.compute_occupancy(o3d.core.Tensor(points[others].astype(np.float32)), nsamples=3).numpy()
        keep[np.flatnonzero(others)[occupied > 0.5]] = False
    idx = np.flatnonzero(keep)
    idx = rng.choice(idx, n_points, replace=len(idx) < n_points)
    points, normals = points[idx], mesh.face_normals[faces[idx]]
    # the evaluation refuses a ground truth that misses the unit cube's faces (few points may miss a wing tip)
    far = np.abs(mesh.vertices).max(axis=1).argmax()
    if np.abs(points).max() < np.abs(mesh.vertices[far]).max() - GT_EXTENT_TOLERANCE / 2:
        axis = np.abs(mesh.vertices[far]).argmax()
        around = np.flatnonzero((mesh.faces == far).any(axis=1))
        outwards = mesh.face_normals[around, axis] * np.sign(mesh.vertices[far, axis])
        nearest = np.linalg.norm(points - mesh.vertices[far], axis=1).argmin()
        points[nearest], normals[nearest] = mesh.vertices[far], mesh.face_normals[around[outwards.argmax()]]
    return points, normals


def model_streams(seed: int, category: str, index: int) -> list[np.random.Generator]:
    """The four random streams of one model: its object, its views, its backgrounds and its surface points."""
    cat_index = sorted(CATEGORIES).index(category)  # stable across runs whatever the order given
    return [np.random.default_rng([seed, cat_index, index, k]) for k in range(4)]


def split_indices(seed: int, category: str, n_models: int) -> dict[str, np.ndarray]:
    """The model indices of the ``train``, ``val`` and ``test`` splits of one category (:func:`split_sizes`)."""
    n_train, n_val, _ = split_sizes(n_models)
    order = np.random.default_rng([seed, sorted(CATEGORIES).index(category)]).permutation(n_models)
    return {"train": order[:n_train], "val": order[n_train : n_train + n_val], "test": order[n_train + n_val :]}


def split_sizes(n_models: int) -> tuple[int, int, int]:
    """(train, val, test) model counts: 10% val and 20% test, at least one model each."""
    if n_models < 3:
        raise DatasetError(f"need at least 3 models (one per split), got {n_models}")
    n_val = max(1, round(0.1 * n_models))
    n_test = max(1, round(0.2 * n_models))
    return n_models - n_val - n_test, n_val, n_test
