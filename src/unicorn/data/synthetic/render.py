"""An independent reference renderer for the synthetic benchmark: open3d ray casting with simple shading.

It deliberately shares nothing with :mod:`unicorn.render`, so that the model's differentiable renderer is not
graded against itself. Cameras follow unicorn's convention (``x_view = x_world @ R + T``, view +X = image
left, +Y up, +Z forward, ``x_ndc = f x / z``, pixel (i, j) centred at NDC ``(1 - (2j+1)/W, 1 - (2i+1)/H)``).
Every pixel is supersampled on a regular ``s x s`` grid and averaged, which anti-aliases both colours and
masks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from unicorn.data.images import DatasetError
from unicorn.data.synthetic.shapes import ProceduralObject
from unicorn.errors import import_open3d

__all__ = ["BACKGROUND_KINDS", "camera_rays", "check_background_kinds", "random_background", "render_object"]

# world-space key light (from above, in front and to the side) and its weight; the rest is ambient + headlight
_KEY_LIGHT = np.array([0.4, 1.0, 0.6]) / np.linalg.norm([0.4, 1.0, 0.6])


def camera_rays(
    R: np.ndarray, T: np.ndarray, image_size: int, fov: float = 30.0, supersample: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions for every (sub)pixel of one camera.

    Args:
        R: (3, 3) world-to-view rotation, T: (3,) translation (``x_view = x_world @ R + T``).
        image_size: output side in pixels.
        fov: full field of view in degrees.
        supersample: rays per pixel along each axis.

    Returns:
        origins (N, 3) and directions (N, 3), N = (image_size * supersample)^2, row-major over the
        supersampled grid.
    """
    n = image_size * supersample
    f = 1.0 / math.tan(math.radians(fov) / 2)
    centers = 1.0 - (2.0 * np.arange(n) + 1.0) / n  # NDC of (sub)pixel centres, decreasing left to right
    y_ndc, x_ndc = np.meshgrid(centers, centers, indexing="ij")
    d_view = np.stack([x_ndc / f, y_ndc / f, np.ones_like(x_ndc)], axis=-1).reshape(-1, 3)
    d_world = d_view @ R.T  # view -> world for directions: x_world = (x_view - T) @ R^T
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origin = -np.asarray(T) @ R.T
    return np.broadcast_to(origin, d_world.shape), d_world


#: the kinds of random background, in the order :func:`random_background` draws from
BACKGROUND_KINDS = ("solid", "gradient", "checker", "noise")


def check_background_kinds(kinds: Sequence[str], name: str = "background kinds") -> tuple[str, ...]:
    """``kinds`` as a tuple, once checked to be some of :data:`BACKGROUND_KINDS`. ``name``: what the setting is
    called in the message (``unicorn-data synth``'s option).

    Raises:
        DatasetError: no kinds, or one that is not a kind of background (the message lists them).
    """
    kinds = (kinds,) if isinstance(kinds, str) else tuple(kinds)
    if not kinds or not set(kinds) <= set(BACKGROUND_KINDS):
        raise DatasetError(f"{name} must be some of {list(BACKGROUND_KINDS)}, got {list(kinds)}")
    return kinds


def random_background(rng: np.random.Generator, size: int, kinds: Sequence[str] = BACKGROUND_KINDS) -> np.ndarray:
    """A random (size, size, 3) background in [0, 1] of one of ``kinds`` (:data:`BACKGROUND_KINDS`, drawn
    uniformly): one colour, a linear gradient between two, a checkerboard of two, or smooth colour noise (a
    coarse grid of random colours, 3 to 7 cells a side, interpolated bilinearly)."""
    kind = rng.choice(check_background_kinds(kinds))
    c0, c1 = rng.uniform(0.05, 0.95, size=(2, 3))
    if kind == "solid":
        return np.broadcast_to(c0, (size, size, 3)).copy()
    if kind == "gradient":
        angle = rng.uniform(0, 2 * math.pi)
        yy, xx = np.mgrid[0:size, 0:size] / max(size - 1, 1) - 0.5
        w = np.clip((xx * math.cos(angle) + yy * math.sin(angle)) + 0.5, 0, 1)[..., None]
        return c0 * (1 - w) + c1 * w
    if kind == "checker":
        cell = int(rng.integers(4, max(5, size // 3)))
        yy, xx = np.mgrid[0:size, 0:size]
        w = (((yy // cell) + (xx // cell)) % 2)[..., None].astype(np.float64)
        return c0 * (1 - w) + c1 * w
    # smooth colour noise: a coarse random grid upsampled bilinearly
    coarse = int(rng.integers(3, 8))
    grid = rng.uniform(0.05, 0.95, size=(coarse, coarse, 3))
    pos = np.linspace(0, coarse - 1, size)
    i0 = np.clip(np.floor(pos).astype(int), 0, coarse - 2)
    t = (pos - i0)[:, None]
    rows = grid[i0] * (1 - t[..., None]) + grid[i0 + 1] * t[..., None]  # (size, coarse, 3)
    return rows[:, i0] * (1 - t[None]) + rows[:, i0 + 1] * t[None]


def render_object(
    obj: ProceduralObject,
    R: np.ndarray,
    T: np.ndarray,
    image_size: int = 64,
    fov: float = 30.0,
    supersample: int = 3,
    backgrounds: np.ndarray | None = None,
    key_light: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast an object from several cameras.

    Shading: ambient 0.35, a world-fixed key light (0.45, ``key_light``) and a headlight (0.25), Lambertian, on normals
    flipped to face the camera; colours come from each part's solid texture at the hit point.

    Args:
        obj: the object (its parts' meshes are in world coordinates).
        R: (V, 3, 3) and T: (V, 3) cameras.
        image_size: side of the output images.
        fov: full field of view in degrees (30 for NMR).
        supersample: rays per pixel along each axis (anti-aliasing).
        backgrounds: (V, S, S, 3) backgrounds in [0, 1], white when None.
        key_light: (3,) world direction towards the key light; None for the default (above, in front, to the
            side). A vertical one, ``(0, 1, 0)``, makes the lighting invariant to turning the camera about +Y.

    Returns:
        images (V, S, S, 3) float32 in [0, 1] and coverage (V, S, S) float32 in [0, 1], the fraction of each
        pixel's rays that hit the object.
    """
    o3d = import_open3d()  # here: reading a generated dataset needs no open3d

    mesh = obj.mesh()
    face_part = obj.face_part()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    V, s, n = len(R), supersample, image_size * supersample
    rays = np.empty((V, n * n, 6), dtype=np.float32)
    for v in range(V):
        origins, dirs = camera_rays(np.asarray(R[v], np.float64), np.asarray(T[v], np.float64), image_size, fov, s)
        rays[v, :, :3], rays[v, :, 3:] = origins, dirs
    rays = rays.reshape(-1, 6)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hit["t_hit"].numpy()
    found = np.isfinite(t_hit)
    prim = hit["primitive_ids"].numpy()[found].astype(np.int64)
    normals = hit["primitive_normals"].numpy()[found].astype(np.float64)
    d = rays[found, 3:].astype(np.float64)
    points = rays[found, :3] + d * t_hit[found, None]

    # two-sided Lambert: orient normals towards the camera
    normals *= -np.sign(np.sum(normals * d, axis=1, keepdims=True) + 1e-12)
    light = _KEY_LIGHT if key_light is None else np.asarray(key_light, np.float64) / np.linalg.norm(key_light)
    shade = 0.35 + 0.45 * np.clip(normals @ light, 0, None) + 0.25 * np.clip(-(normals * d).sum(1), 0, None)
    colors = np.empty((len(prim), 3))
    part_of_hit = face_part[prim]
    for k, part in enumerate(obj.parts):
        sel = part_of_hit == k
        if sel.any():
            colors[sel] = part.texture(points[sel])
    colors = np.clip(colors * np.minimum(shade, 1.0)[:, None], 0, 1)

    rgb = np.zeros((V * n * n, 3))
    rgb[found] = colors
    cover = found.astype(np.float64)
    # average each s x s block of subpixels
    rgb = rgb.reshape(V, image_size, s, image_size, s, 3).mean(axis=(2, 4))
    cover = cover.reshape(V, image_size, s, image_size, s).mean(axis=(2, 4))
    bg = np.ones((V, image_size, image_size, 3)) if backgrounds is None else np.asarray(backgrounds, np.float64)
    images = rgb + (1 - cover[..., None]) * bg
    return images.astype(np.float32).clip(0, 1), cover.astype(np.float32)
