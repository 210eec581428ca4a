"""Procedural object categories assembled from trimesh primitives, with per-instance proportions.

Objects are built in UNICORN's object frame: +Y up, front towards +X, bilateral symmetry about the XY plane.
Each part carries a procedural solid texture (a colour pattern evaluated at 3D surface points), and the whole
object is normalised as ShapeNet is for the NMR renderings: bounding-box centre at the origin and longest
bounding-box edge equal to 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from trimesh import creation
from trimesh.transformations import rotation_matrix

from unicorn.data.images import DatasetError

__all__ = ["CATEGORIES", "Part", "ProceduralObject", "Texture", "build_object"]

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


# ---------------------------------------------------------------------------------------------------------
# primitive helpers (all sizes are before normalisation)


def _box(extents: tuple[float, float, float], center: tuple[float, float, float]) -> trimesh.Trimesh:
    return creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def _cylinder(radius: float, height: float, center, axis: str = "y", sections: int = 20) -> trimesh.Trimesh:
    """Cylinder along a world axis (trimesh builds them along Z)."""
    mesh = creation.cylinder(radius=radius, height=height, sections=sections)
    if axis == "y":
        mesh.apply_transform(rotation_matrix(-math.pi / 2, [1, 0, 0]))
    elif axis == "x":
        mesh.apply_transform(rotation_matrix(math.pi / 2, [0, 1, 0]))
    mesh.apply_translation(center)
    return mesh


def _frustum(r_bottom: float, r_top: float, height: float, center, sections: int = 24) -> trimesh.Trimesh:
    """Truncated cone along +Y (convex hull of two circles)."""
    a = np.linspace(0, 2 * math.pi, sections, endpoint=False)
    ring = np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], axis=1)
    pts = np.concatenate([ring * r_bottom + [0, -height / 2, 0], ring * r_top + [0, height / 2, 0]])
    return trimesh.convex.convex_hull(pts + np.asarray(center))


def _hull(points: np.ndarray) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64))


def _palette_color(rng: Rng, saturation: tuple[float, float] = (0.3, 0.9)) -> np.ndarray:
    """A random colour from HSV ranges that keeps it away from pure white (the NMR background)."""
    h = rng.uniform(0, 1)
    s = rng.uniform(*saturation)
    v = rng.uniform(0.35, 0.9)
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def _texture(rng: Rng, patterned: float = 0.5) -> Texture:
    """Solid colour, or (with probability ``patterned``) stripes / checker / gradient of two colours."""
    c0 = _palette_color(rng)
    if rng.random() >= patterned:
        return Texture("solid", np.stack([c0, c0]))
    c1 = _palette_color(rng)
    kind = str(rng.choice(["stripes", "checker", "gradient"]))
    return Texture(kind, np.stack([c0, c1]), frequency=float(rng.uniform(2.0, 6.0)), axis=int(rng.integers(0, 3)))


def _u(rng: Rng, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


# ---------------------------------------------------------------------------------------------------------
# categories: each builder returns (parts as [(name, [meshes])], params)


def _chair(rng: Rng) -> tuple[list[tuple[str, list[trimesh.Trimesh]]], dict[str, Any]]:
    p = {
        "seat_width": _u(rng, 0.4, 0.6),
        "seat_depth": _u(rng, 0.4, 0.6),
        "seat_thickness": _u(rng, 0.04, 0.09),
        "seat_height": _u(rng, 0.35, 0.5),
        "back_height": _u(rng, 0.3, 0.7),
        "back_thickness": _u(rng, 0.03, 0.07),
        "back_tilt_deg": _u(rng, 0, 15),
        "leg_radius": _u(rng, 0.018, 0.04),
        "legs": str(rng.choice(["four", "four", "four_square", "pedestal"])),
        "arms": bool(rng.random() < 0.3),
    }
    w, d, t, h = p["seat_width"], p["seat_depth"], p["seat_thickness"], p["seat_height"]
    seat = _box((d, t, w), (0, h, 0))
    bh, bt = p["back_height"], p["back_thickness"]
    back = _box((bt, bh, w), (0, bh / 2, 0))
    back.apply_transform(rotation_matrix(math.radians(p["back_tilt_deg"]), [0, 0, 1]))
    back.apply_translation((-d / 2 + bt / 2, h + t / 2, 0))
    r = p["leg_radius"]
    legs = []
    if p["legs"] == "pedestal":
        legs.append(_cylinder(r * 1.5, h - 0.05, (0, (h - 0.05) / 2 + 0.05, 0)))
        for k in range(5):
            foot = _box((0.3 * max(w, d), 0.04, 0.05), (0.15 * max(w, d), 0.03, 0))
            foot.apply_transform(rotation_matrix(2 * math.pi * k / 5, [0, 1, 0]))
            legs.append(foot)
    else:
        for sx in (-1, 1):
            for sz in (-1, 1):
                c = (sx * (d / 2 - r * 1.5), (h - t / 2) / 2, sz * (w / 2 - r * 1.5))
                legs.append(
                    _box((2 * r, h - t / 2, 2 * r), c) if p["legs"] == "four_square" else _cylinder(r, h - t / 2, c)
                )
    parts = [("seat", [seat]), ("back", [back]), ("legs", legs)]
    if p["arms"]:
        arms = [_box((d * 0.8, 0.04, 0.04), (0, h + 0.2, sz * (w / 2 - 0.02))) for sz in (-1, 1)]
        arms += [_box((0.04, 0.2, 0.04), (d * 0.3, h + 0.1, sz * (w / 2 - 0.02))) for sz in (-1, 1)]
        parts.append(("arms", arms))
    return parts, p


def _table(rng: Rng) -> tuple[list[tuple[str, list[trimesh.Trimesh]]], dict[str, Any]]:
    p = {
        "top": str(rng.choice(["rect", "rect", "round"])),
        "length": _u(rng, 0.8, 1.6),
        "width": _u(rng, 0.5, 1.0),
        "thickness": _u(rng, 0.03, 0.08),
        "height": _u(rng, 0.45, 0.8),
        "leg_radius": _u(rng, 0.02, 0.05),
        "legs": str(rng.choice(["four", "four", "pedestal"])),
        "shelf": bool(rng.random() < 0.3),
    }
    L, W, t, h, r = p["length"], p["width"], p["thickness"], p["height"], p["leg_radius"]
    if p["top"] == "round":
        W = L = min(L, 1.1)
        top = _cylinder(L / 2, t, (0, h - t / 2, 0), sections=32)
    else:
        top = _box((L, t, W), (0, h - t / 2, 0))
    legs = []
    if p["legs"] == "pedestal":
        legs.append(_cylinder(r * 2, h - t, (0, (h - t) / 2, 0)))
        legs.append(_cylinder(min(L, W) * 0.3, 0.04, (0, 0.02, 0), sections=32))
    else:
        inset = 0.7 if p["top"] == "round" else 0.9
        for sx in (-1, 1):
            for sz in (-1, 1):
                legs.append(_cylinder(r, h - t, (sx * inset * (L / 2 - r), (h - t) / 2, sz * inset * (W / 2 - r))))
    parts = [("top", [top]), ("legs", legs)]
    if p["shelf"] and p["legs"] == "four":
        inset = 0.7 if p["top"] == "round" else 0.9
        parts.append(("shelf", [_box((inset * L * 0.9, 0.03, inset * W * 0.9), (0, h * 0.25, 0))]))
    return parts, p


def _car(rng: Rng) -> tuple[list[tuple[str, list[trimesh.Trimesh]]], dict[str, Any]]:
    p = {
        "length": 1.0,
        "width": _u(rng, 0.38, 0.5),
        "body_height": _u(rng, 0.12, 0.22),
        "wheel_radius": _u(rng, 0.07, 0.11),
        "wheel_width": _u(rng, 0.05, 0.08),
        "wheel_inset": _u(rng, 0.14, 0.22),
        "cabin_length": _u(rng, 0.35, 0.65),
        "cabin_top_ratio": _u(rng, 0.5, 0.9),
        "cabin_height": _u(rng, 0.1, 0.2),
        "cabin_offset": _u(rng, -0.15, 0.05),
        "spoiler": bool(rng.random() < 0.2),
    }
    L, W, bh, wr = p["length"], p["width"], p["body_height"], p["wheel_radius"]
    base = wr * 0.6
    body = _box((L, bh, W), (0, base + bh / 2, 0))
    cl, ch, co = p["cabin_length"] * L, p["cabin_height"], p["cabin_offset"] * L
    ct = cl * p["cabin_top_ratio"]
    y0, y1, cw = base + bh, base + bh + ch, 0.9 * W
    cabin = _hull(
        [(co + sx * cl / 2, y0, sz * cw / 2) for sx in (-1, 1) for sz in (-1, 1)]
        + [(co + sx * ct / 2, y1, sz * cw * 0.85 / 2) for sx in (-1, 1) for sz in (-1, 1)]
    )
    wheels = [
        _cylinder(
            wr,
            p["wheel_width"],
            (sx * (L / 2 - p["wheel_inset"]), wr, sz * (W / 2 - p["wheel_width"] / 3)),
            axis="z",
        )
        for sx in (-1, 1)
        for sz in (-1, 1)
    ]
    parts = [("body", [body]), ("cabin", [cabin]), ("wheels", wheels)]
    if p["spoiler"]:
        parts.append(
            (
                "spoiler",
                [
                    _box((0.08, 0.02, W * 0.9), (-L / 2 + 0.05, y0 + 0.06, 0)),
                    _box((0.03, 0.06, 0.03), (-L / 2 + 0.05, y0 + 0.03, 0)),
                ],
            )
        )
    return parts, p


def _wing(
    root_x: float,
    root_chord: float,
    tip_chord: float,
    half_span: float,
    sweep_deg: float,
    thickness: float,
    y: float,
    side: int,
    dihedral: float = 0.0,
) -> trimesh.Trimesh:
    """Swept trapezoidal wing (one side) as a convex hull, root at z = 0, tip at z = side * half_span."""
    back = half_span * math.tan(math.radians(sweep_deg))
    pts = []
    for dy in (-thickness / 2, thickness / 2):
        pts += [(root_x + root_chord / 2, y + dy, 0), (root_x - root_chord / 2, y + dy, 0)]
        tip_x = root_x - back
        pts += [
            (tip_x + tip_chord / 2, y + dy + dihedral, side * half_span),
            (tip_x - tip_chord / 2, y + dy + dihedral, side * half_span),
        ]
    return _hull(pts)


def _airplane(rng: Rng) -> tuple[list[tuple[str, list[trimesh.Trimesh]]], dict[str, Any]]:
    p = {
        "length": _u(rng, 0.9, 1.0),
        "fuselage_radius": _u(rng, 0.035, 0.075),
        "span": _u(rng, 0.7, 1.1),
        "chord": _u(rng, 0.12, 0.25),
        "taper": _u(rng, 0.3, 0.8),
        "sweep_deg": _u(rng, 0, 35),
        "wing_x": _u(rng, -0.1, 0.1),
        "dihedral": _u(rng, 0.0, 0.06),
        "tail_span": _u(rng, 0.25, 0.4),
        "fin_height": _u(rng, 0.1, 0.2),
        "engines": int(rng.choice([0, 2, 2, 4])),
    }
    L, fr = p["length"], p["fuselage_radius"]
    fuselage = creation.capsule(height=L - 2 * fr, radius=fr, count=[16, 16])
    fuselage.apply_transform(rotation_matrix(math.pi / 2, [0, 1, 0]))
    c = p["chord"]
    wings = [
        _wing(p["wing_x"], c, c * p["taper"], p["span"] / 2, p["sweep_deg"], 0.02, 0.0, s, p["dihedral"])
        for s in (-1, 1)
    ]
    tx = -L / 2 + 0.08
    tail = [_wing(tx, c * 0.6, c * 0.3, p["tail_span"] / 2, p["sweep_deg"], 0.015, fr * 0.3, s) for s in (-1, 1)]
    fh = p["fin_height"]
    fin = _hull(
        [
            (tx + c * 0.35, 0, -0.008),
            (tx - c * 0.3, 0, -0.008),
            (tx + c * 0.35, 0, 0.008),
            (tx - c * 0.3, 0, 0.008),
            (tx - c * 0.1, fh, -0.006),
            (tx - c * 0.3, fh, -0.006),
            (tx - c * 0.1, fh, 0.006),
            (tx - c * 0.3, fh, 0.006),
        ]
    )
    parts = [("fuselage", [fuselage]), ("wings", wings), ("tail", tail + [fin])]
    if p["engines"]:
        zs = [0.3] if p["engines"] == 2 else [0.22, 0.4]
        tan_sweep = math.tan(math.radians(p["sweep_deg"]))
        # under the wing, following its sweep
        engines = [
            _cylinder(
                fr * 0.6,
                c * 0.8,
                (p["wing_x"] + 0.1 * c - z * p["span"] / 2 * tan_sweep, -fr * 0.9, s * z * p["span"] / 2),
                axis="x",
                sections=14,
            )
            for z in zs
            for s in (-1, 1)
        ]
        parts.append(("engines", engines))
    return parts, p


def _lamp(rng: Rng) -> tuple[list[tuple[str, list[trimesh.Trimesh]]], dict[str, Any]]:
    p = {
        "base": str(rng.choice(["disc", "box"])),
        "base_radius": _u(rng, 0.12, 0.22),
        "stem_height": _u(rng, 0.5, 0.9),
        "stem_radius": _u(rng, 0.012, 0.025),
        "arm": bool(rng.random() < 0.4),
        "arm_length": _u(rng, 0.15, 0.35),
        "shade": str(rng.choice(["cone", "cone", "sphere", "cylinder"])),
        "shade_bottom": _u(rng, 0.15, 0.3),
        "shade_top": _u(rng, 0.05, 0.15),
        "shade_height": _u(rng, 0.15, 0.3),
    }
    br, sh, sr = p["base_radius"], p["stem_height"], p["stem_radius"]
    base = (
        _cylinder(br, 0.04, (0, 0.02, 0), sections=28)
        if p["base"] == "disc"
        else _box((2 * br, 0.05, 2 * br * 0.8), (0, 0.025, 0))
    )
    stem = [_cylinder(sr, sh, (0, sh / 2, 0))]
    top = np.array([0.0, sh, 0.0])
    if p["arm"]:
        arm = _cylinder(sr, p["arm_length"], (p["arm_length"] / 2, sh, 0), axis="x")
        stem.append(arm)
        top = np.array([p["arm_length"], sh, 0.0])
    hh = p["shade_height"]
    if p["shade"] == "sphere":
        shade = creation.icosphere(subdivisions=2, radius=p["shade_bottom"] * 0.8)
        shade.apply_translation(top + [0, p["shade_bottom"] * 0.5, 0])
    elif p["shade"] == "cylinder":
        shade = _cylinder(p["shade_bottom"] * 0.8, hh, top + [0, hh * 0.3, 0], sections=28)
    else:
        shade = _frustum(p["shade_bottom"], p["shade_top"], hh, top + [0, hh * 0.3, 0])
    return [("base", [base]), ("stem", stem), ("shade", [shade])], p


def _mug(rng: Rng) -> tuple[list[tuple[str, list[trimesh.Trimesh]]], dict[str, Any]]:
    p = {
        "radius": _u(rng, 0.28, 0.45),
        "height": _u(rng, 0.6, 1.0),
        "wall": _u(rng, 0.025, 0.05),
        "handle_radius": _u(rng, 0.14, 0.24),
        "handle_thickness": _u(rng, 0.025, 0.05),
        "handle_height": _u(rng, 0.4, 0.6),
    }
    r, h, wall = p["radius"], p["height"], p["wall"]
    body = creation.annulus(r_min=r - wall, r_max=r, height=h, sections=40)
    body.apply_transform(rotation_matrix(-math.pi / 2, [1, 0, 0]))
    body.apply_translation((0, h / 2, 0))
    bottom = _cylinder(r - wall / 2, wall, (0, wall / 2, 0), sections=40)
    hr = p["handle_radius"] * h
    handle = creation.torus(major_radius=hr, minor_radius=p["handle_thickness"], major_sections=32, minor_sections=12)
    handle.apply_translation((r, p["handle_height"] * h, 0))
    # keep only the outer half of the ring: the inner half would poke into the cup
    outside = handle.vertices[handle.faces][:, :, 0].min(axis=1) > r - wall
    handle.update_faces(outside)
    handle.remove_unreferenced_vertices()
    return [("body", [body, bottom]), ("handle", [handle])], p


#: category name -> (pseudo synset id, builder)
CATEGORIES: dict[str, tuple[str, Callable[[Rng], tuple[list, dict]]]] = {
    "chair": ("90000001", _chair),
    "table": ("90000002", _table),
    "car": ("90000003", _car),
    "airplane": ("90000004", _airplane),
    "lamp": ("90000005", _lamp),
    "mug": ("90000006", _mug),
}


def build_object(category: str, rng: Rng, patterned: float = 0.5) -> ProceduralObject:
    """Sample one normalised instance of ``category``.

    Args:
        category: a key of :data:`CATEGORIES`.
        rng: numpy generator; the object is a deterministic function of its state.
        patterned: probability that a part gets a two-colour pattern rather than a solid colour.

    Returns:
        The object, centred with its longest bounding-box edge equal to 1.
    """
    if category not in CATEGORIES:
        raise DatasetError(f"unknown synthetic category {category!r}; choose from {sorted(CATEGORIES)}")
    _, builder = CATEGORIES[category]
    groups, params = builder(rng)
    parts = [Part(name, trimesh.util.concatenate(meshes), _texture(rng, patterned)) for name, meshes in groups]
    params = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in params.items()}
    params["textures"] = {part.name: part.texture.to_json() for part in parts}
    return ProceduralObject(category, parts, params).normalise()
