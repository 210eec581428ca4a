"""The building blocks of the procedural objects: solid textures, primitive meshes and palette colours.

Every category builder (:mod:`.furniture`, :mod:`.vehicles`, :mod:`.household`) assembles its parts from these;
all sizes are before the object's normalisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from trimesh import creation
from trimesh.transformations import rotation_matrix

__all__ = [
    "Groups",
    "Rng",
    "Texture",
    "body_color",
    "box",
    "contrasting",
    "cylinder",
    "extrude",
    "frustum",
    "hull",
    "hsv",
    "near",
    "palette_color",
    "random_texture",
    "solid",
    "uniform",
]

Rng = np.random.Generator


@dataclass
class Texture:
    """Solid texture: ``kind`` (solid, stripes, checker, gradient), two colours, a frequency, an axis."""

    kind: str
    colors: np.ndarray  # (2, 3) in [0, 1]
    frequency: float = 4.0
    axis: int = 0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Colours (N, 3) of surface points (N, 3) in the normalised object frame."""
        c0, c1 = self.colors
        if self.kind == "solid":
            w = np.zeros(len(points))
        elif self.kind == "stripes":
            w = (np.floor(points[:, self.axis] * self.frequency * 2) % 2).astype(np.float64)
        elif self.kind == "checker":
            w = (np.floor(points * self.frequency * 2).sum(axis=1) % 2).astype(np.float64)
        elif self.kind == "gradient":
            w = np.clip(points[:, self.axis] + 0.5, 0.0, 1.0)
        else:
            raise ValueError(f"unknown texture kind {self.kind!r}")
        return c0[None] * (1 - w[:, None]) + c1[None] * w[:, None]

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "colors": self.colors.round(4).tolist(),
            "frequency": self.frequency,
            "axis": self.axis,
        }


#: what a category builder returns besides its parameters: its parts as ``[(name, [meshes], texture or None)]``;
#: a part without a texture gets a random one (see :func:`~unicorn.data.synthetic.shapes.build_object`)
Groups = list[tuple[str, list[trimesh.Trimesh], Texture | None]]


def box(extents: tuple[float, float, float], center: tuple[float, float, float]) -> trimesh.Trimesh:
    return creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def cylinder(radius: float, height: float, center, axis: str = "y", sections: int = 20) -> trimesh.Trimesh:
    """Cylinder along a world axis (trimesh builds them along Z)."""
    mesh = creation.cylinder(radius=radius, height=height, sections=sections)
    if axis == "y":
        mesh.apply_transform(rotation_matrix(-math.pi / 2, [1, 0, 0]))
    elif axis == "x":
        mesh.apply_transform(rotation_matrix(math.pi / 2, [0, 1, 0]))
    mesh.apply_translation(center)
    return mesh


def frustum(r_bottom: float, r_top: float, height: float, center, sections: int = 24) -> trimesh.Trimesh:
    """Truncated cone along +Y (convex hull of two circles)."""
    a = np.linspace(0, 2 * math.pi, sections, endpoint=False)
    ring = np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], axis=1)
    pts = np.concatenate([ring * r_bottom + [0, -height / 2, 0], ring * r_top + [0, height / 2, 0]])
    return trimesh.convex.convex_hull(pts + np.asarray(center))


def hull(points: np.ndarray) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64))


def hsv(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def palette_color(
    rng: Rng, saturation: tuple[float, float] = (0.3, 0.9), value: tuple[float, float] = (0.35, 0.9)
) -> np.ndarray:
    """A random colour from HSV ranges that keeps it away from pure white (the NMR background)."""
    return hsv(rng.uniform(0, 1), rng.uniform(*saturation), rng.uniform(*value))


def body_color(rng: Rng) -> np.ndarray:
    """An object's main colour: any hue, clearly saturated, so that colour is an instance property."""
    return palette_color(rng, saturation=(0.45, 1.0), value=(0.35, 0.92))


def contrasting(rng: Rng, ref: np.ndarray, min_dist: float = 0.35, **ranges: tuple[float, float]) -> np.ndarray:
    """A palette colour at least ``min_dist`` (Euclidean RGB) from ``ref`` (the farthest of a few draws)."""
    best, best_d = ref, -1.0
    for _ in range(32):
        c = palette_color(rng, **ranges)
        d = float(np.linalg.norm(c - ref))
        if d >= min_dist:
            return c
        if d > best_d:
            best, best_d = c, d
    return best


def near(rng: Rng, rgb: tuple[float, float, float], spread: float = 0.05) -> np.ndarray:
    """A fixed colour (lights, glass, tyres) with a little per-instance jitter."""
    return np.clip(np.asarray(rgb) + rng.uniform(-spread, spread, 3), 0.0, 1.0)


def solid(color: np.ndarray) -> Texture:
    return Texture("solid", np.stack([color, color]))


def random_texture(rng: Rng, patterned: float = 0.5, base: np.ndarray | None = None) -> Texture:
    """Solid colour, or (with probability ``patterned``) stripes / checker / gradient of two colours.

    ``base`` fixes the first colour (an instance's main colour); otherwise it is drawn from the palette.
    """
    c0 = palette_color(rng) if base is None else base
    if rng.random() >= patterned:
        return solid(c0)
    c1 = contrasting(rng, c0, 0.25)
    kind = str(rng.choice(["stripes", "checker", "gradient"]))
    return Texture(kind, np.stack([c0, c1]), frequency=float(rng.uniform(2.0, 6.0)), axis=int(rng.integers(0, 3)))


def uniform(rng: Rng, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def extrude(profile: list[tuple[float, float]], half_width: float) -> trimesh.Trimesh:
    """Convex solid of a convex side profile ``[(x, y), ...]`` extruded over z in [-half_width, half_width]."""
    return hull([(x, y, z) for x, y in profile for z in (-half_width, half_width)])
