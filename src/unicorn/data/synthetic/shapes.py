"""Procedural object categories assembled from trimesh primitives, with per-instance proportions.

Objects are built in UNICORN's object frame: +Y up, front towards +X, bilateral symmetry about the XY plane.
No category is front/back symmetric: a car has a long bonnet, a short boot, white head and red tail lights; a
chair its back; an airplane its cockpit and fin; a desk its drawers and back panel; a lamp its forward arm; a mug
its handle. So a view and the same view turned by 180 degrees in azimuth are different pictures, and the pose
of an image is not ambiguous. Proportions, part shapes and the main colour (any hue, saturated) vary per
instance. Each part carries a procedural solid texture (a colour pattern evaluated at 3D surface points), and the whole
object is normalised as ShapeNet is for the NMR renderings: bounding-box centre at the origin and longest
bounding-box edge equal to 1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from unicorn.data.images import DatasetError
from unicorn.data.synthetic.furniture import chair, table
from unicorn.data.synthetic.household import lamp, mug
from unicorn.data.synthetic.primitives import Groups, Rng, Texture, random_texture
from unicorn.data.synthetic.vehicles import airplane, car

__all__ = ["CATEGORIES", "Part", "ProceduralObject", "build_object"]


@dataclass
class Part:
    """One named primitive group of an object, with its texture."""

    name: str
    mesh: trimesh.Trimesh
    texture: Texture


@dataclass
class ProceduralObject:
    """An assembled object: its parts (normalised together) and the parameters that produced it."""

    category: str
    parts: list[Part]
    params: dict[str, Any] = field(default_factory=dict)

    def mesh(self) -> trimesh.Trimesh:
        """All parts concatenated into one mesh (parts may interpenetrate)."""
        return trimesh.util.concatenate([p.mesh for p in self.parts])

    def face_part(self) -> np.ndarray:
        """(F,) index of the part each face of :meth:`mesh` belongs to."""
        return np.concatenate([np.full(len(p.mesh.faces), i) for i, p in enumerate(self.parts)])

    def normalise(self) -> ProceduralObject:
        """Centre the bounding box on the origin and scale its longest edge to 1 (in place)."""
        lo, hi = self.mesh().bounds
        center, scale = (lo + hi) / 2, 1.0 / float((hi - lo).max())
        for p in self.parts:
            p.mesh.apply_translation(-center)
            p.mesh.apply_scale(scale)
        self.params["normalisation"] = {"center": center.round(6).tolist(), "scale": round(scale, 6)}
        return self


#: category name -> (pseudo synset id, builder)
CATEGORIES: dict[str, tuple[str, Callable[[Rng], tuple[Groups, dict]]]] = {
    "chair": ("90000001", chair),
    "table": ("90000002", table),
    "car": ("90000003", car),
    "airplane": ("90000004", airplane),
    "lamp": ("90000005", lamp),
    "mug": ("90000006", mug),
}


def build_object(category: str, rng: Rng, patterned: float = 0.5) -> ProceduralObject:
    """Sample one normalised instance of ``category``.

    Args:
        category: a key of :data:`CATEGORIES`.
        rng: numpy generator; the object is a deterministic function of its state.
        patterned: probability that a part without a designed colour (legs, arms) gets a two-colour pattern
            rather than a solid colour.

    Returns:
        The object, centred with its longest bounding-box edge equal to 1.
    """
    if category not in CATEGORIES:
        raise DatasetError(f"unknown synthetic category {category!r}; choose from {sorted(CATEGORIES)}")
    _, builder = CATEGORIES[category]
    groups, params = builder(rng)
    parts = [
        Part(name, trimesh.util.concatenate(meshes), texture if texture is not None else random_texture(rng, patterned))
        for name, meshes, texture in groups
    ]
    params = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in params.items()}
    params["textures"] = {part.name: part.texture.to_json() for part in parts}
    return ProceduralObject(category, parts, params).normalise()
