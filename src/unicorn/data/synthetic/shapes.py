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


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def _palette_color(
    rng: Rng, saturation: tuple[float, float] = (0.3, 0.9), value: tuple[float, float] = (0.35, 0.9)
) -> np.ndarray:
    """A random colour from HSV ranges that keeps it away from pure white (the NMR background)."""
    return _hsv(rng.uniform(0, 1), rng.uniform(*saturation), rng.uniform(*value))


def _body_color(rng: Rng) -> np.ndarray:
    """An object's main colour: any hue, clearly saturated, so that colour is an instance property."""
    return _palette_color(rng, saturation=(0.45, 1.0), value=(0.35, 0.92))


def _contrasting(rng: Rng, ref: np.ndarray, min_dist: float = 0.35, **ranges: tuple[float, float]) -> np.ndarray:
    """A palette colour at least ``min_dist`` (Euclidean RGB) from ``ref`` (the farthest of a few draws)."""
    best, best_d = ref, -1.0
    for _ in range(32):
        c = _palette_color(rng, **ranges)
        d = float(np.linalg.norm(c - ref))
        if d >= min_dist:
            return c
        if d > best_d:
            best, best_d = c, d
    return best


def _near(rng: Rng, rgb: tuple[float, float, float], spread: float = 0.05) -> np.ndarray:
    """A fixed colour (lights, glass, tyres) with a little per-instance jitter."""
    return np.clip(np.asarray(rgb) + rng.uniform(-spread, spread, 3), 0.0, 1.0)


def _solid(color: np.ndarray) -> Texture:
    return Texture("solid", np.stack([color, color]))


def _texture(rng: Rng, patterned: float = 0.5, base: np.ndarray | None = None) -> Texture:
    """Solid colour, or (with probability ``patterned``) stripes / checker / gradient of two colours.

    ``base`` fixes the first colour (an instance's main colour); otherwise it is drawn from the palette.
    """
    c0 = _palette_color(rng) if base is None else base
    if rng.random() >= patterned:
        return _solid(c0)
    c1 = _contrasting(rng, c0, 0.25)
    kind = str(rng.choice(["stripes", "checker", "gradient"]))
    return Texture(kind, np.stack([c0, c1]), frequency=float(rng.uniform(2.0, 6.0)), axis=int(rng.integers(0, 3)))


def _u(rng: Rng, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _extrude(profile: list[tuple[float, float]], half_width: float) -> trimesh.Trimesh:
    """Convex solid of a convex side profile ``[(x, y), ...]`` extruded over z in [-half_width, half_width]."""
    return _hull([(x, y, z) for x, y in profile for z in (-half_width, half_width)])


# ---------------------------------------------------------------------------------------------------------
# categories: each builder returns (parts as [(name, [meshes], texture or None)], params); a part without a
# texture gets a random one (see build_object). Every category has a front (+X) that its back does not look
# like, so that a view and the same view turned by 180 degrees are different pictures.

Groups = list[tuple[str, list[trimesh.Trimesh], Texture | None]]


def _chair(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    p = {
        "seat_width": _u(rng, 0.38, 0.65),
        "seat_depth": _u(rng, 0.38, 0.62),
        "seat_thickness": _u(rng, 0.03, 0.1),
        "seat_height": _u(rng, 0.32, 0.52),
        "back_height": _u(rng, 0.3, 0.75),
        "back_thickness": _u(rng, 0.03, 0.07),
        "back_tilt_deg": _u(rng, 0, 18),
        "back_style": str(rng.choice(["solid", "solid", "slats", "frame"])),
        "leg_radius": _u(rng, 0.015, 0.04),
        "legs": str(rng.choice(["four", "four", "four_square", "pedestal"])),
        "arms": bool(rng.random() < 0.3),
    }
    w, d, t, h = p["seat_width"], p["seat_depth"], p["seat_thickness"], p["seat_height"]
    seat = _box((d, t, w), (0, h, 0))
    bh, bt = p["back_height"], p["back_thickness"]
    if p["back_style"] == "solid":
        back = [_box((bt, bh, w), (0, bh / 2, 0))]
    else:  # two posts and a top rail, with vertical slats or nothing between them
        post = 0.06 * w + 0.02
        back = [_box((bt, bh, post), (0, bh / 2, sz * (w - post) / 2)) for sz in (-1, 1)]
        back.append(_box((bt, 0.22 * bh, w), (0, bh * 0.89, 0)))
        if p["back_style"] == "slats":
            n = 3 if w < 0.5 else 4
            back += [_box((bt * 0.7, bh, 0.04), (0, bh / 2, z)) for z in np.linspace(-w / 2, w / 2, n + 2)[1:-1]]
    back = trimesh.util.concatenate(back)
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
    seat_color = _body_color(rng)
    back_color = seat_color if rng.random() < 0.5 else _contrasting(rng, seat_color, 0.3)
    parts: Groups = [("seat", [seat], _texture(rng, 0.3, seat_color)), ("back", [back], _solid(back_color))]
    parts.append(("legs", legs, None))
    if p["arms"]:
        arms = [_box((d * 0.8, 0.04, 0.04), (0, h + 0.2, sz * (w / 2 - 0.02))) for sz in (-1, 1)]
        arms += [_box((0.04, 0.2, 0.04), (d * 0.3, h + 0.1, sz * (w / 2 - 0.02))) for sz in (-1, 1)]
        parts.append(("arms", arms, None))
    return parts, p


def _table(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A desk: drawers hang under the top at the front, a modesty panel closes the back between the legs."""
    p = {
        "length": _u(rng, 0.8, 1.6),  # along z (the long side faces the front)
        "depth": _u(rng, 0.45, 0.85),
        "thickness": _u(rng, 0.03, 0.08),
        "height": _u(rng, 0.45, 0.8),
        "leg_radius": _u(rng, 0.02, 0.05),
        "legs": str(rng.choice(["round", "square"])),
        "drawers": int(rng.integers(1, 4)),
        "drawer_height": _u(rng, 0.1, 0.2),
        "overhang": _u(rng, 0.1, 0.25),  # the top reaches past the front legs by this share of the depth
        "panel_drop": _u(rng, 0.4, 0.8),  # share of the leg height the back panel covers
        "shelf": bool(rng.random() < 0.3),
    }
    L, D, t, h, r = p["length"], p["depth"], p["thickness"], p["height"], p["leg_radius"]
    top = _box((D, t, L), (0, h - t / 2, 0))
    legs = []
    xf, xb = D / 2 - p["overhang"] * D - r, -0.96 * (D / 2 - r)  # front and back leg positions
    for x in (xb, xf):
        for sz in (-1, 1):
            c = (x, (h - t) / 2, sz * 0.95 * (L / 2 - r))
            legs.append(_cylinder(r, h - t, c) if p["legs"] == "round" else _box((2 * r, h - t, 2 * r), c))
    drop = p["panel_drop"] * (h - t)
    panel = _box((0.02, drop, 0.95 * L - 2 * r), (xb, h - t - drop / 2, 0))
    # drawers side by side under the front edge, each with a knob
    n, dh = p["drawers"], p["drawer_height"]
    dw = 0.9 * L / max(n, 2)
    drawers, knobs = [], []
    for k in range(n):
        z = (k - (n - 1) / 2) * dw
        drawers.append(_box((0.6 * D, dh, 0.94 * dw), (D / 2 - 0.3 * D - 0.01, h - t - dh / 2, z)))
        knobs.append(_box((0.03, 0.03, 0.08), (D / 2 - 0.005, h - t - dh / 2, z)))
    top_color = _body_color(rng)
    leg_color = _contrasting(rng, top_color, 0.3)
    drawer_color = _contrasting(rng, top_color, 0.35)
    parts: Groups = [
        ("top", [top], _texture(rng, 0.3, top_color)),
        ("legs", legs + [panel], _solid(leg_color)),
        ("drawers", drawers, _solid(drawer_color)),
        ("knobs", knobs, _solid(_near(rng, (0.1, 0.1, 0.1)))),
    ]
    if p["shelf"]:
        parts.append(("shelf", [_box((0.8 * D, 0.03, 0.85 * L), (0, h * 0.2, 0))], _solid(leg_color)))
    return parts, p


#: car body types: (bonnet, boot) length ranges as shares of the length, body height, cabin height share,
#: windscreen angle from the horizontal (degrees), rear window's share of the cabin's slopes
_CAR_TYPES: dict[str, dict[str, tuple[float, float]]] = {
    "sedan": {"bonnet": (0.32, 0.4), "boot": (0.14, 0.2), "body": (0.13, 0.19), "windscreen": (25, 35)},
    "hatchback": {"bonnet": (0.26, 0.34), "boot": (0.03, 0.08), "body": (0.14, 0.2), "windscreen": (25, 38)},
    "suv": {"bonnet": (0.24, 0.3), "boot": (0.03, 0.07), "body": (0.2, 0.27), "windscreen": (32, 45)},
    "coupe": {"bonnet": (0.36, 0.44), "boot": (0.12, 0.18), "body": (0.11, 0.15), "windscreen": (20, 28)},
}


def _car(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A car facing +X: a long bonnet and a short boot, a sloped windscreen, white head and red tail lights.

    The body is the side profile (low nose, bonnet sloping up to the windscreen, vertical tail) extruded
    across the width; the cabin is a glass house (dark glass) under a roof of the body colour. The front
    carries a dark bumper and grille between warm-white head lights, the tail red lights.
    """
    kind = str(rng.choice(list(_CAR_TYPES)))
    ranges = _CAR_TYPES[kind]
    p: dict[str, Any] = {
        "type": kind,
        "length": 1.0,
        "width": _u(rng, 0.36, 0.5),
        "body_height": _u(rng, *ranges["body"]),
        "bonnet": _u(rng, *ranges["bonnet"]),
        "boot": _u(rng, *ranges["boot"]),
        "nose_height": _u(rng, 0.5, 0.8),  # share of the body height at the very front
        "windscreen_deg": _u(rng, *ranges["windscreen"]),
        "roof_share": _u(rng, 0.35, 0.6) if kind != "suv" else _u(rng, 0.6, 0.75),
        "rear_slope_share": _u(rng, 0.2, 0.45),  # of what the roof leaves, the rest is the windscreen's run
        "wheel_radius": _u(rng, 0.065, 0.095) * (1.2 if kind == "suv" else 1.0),
        "wheel_width": _u(rng, 0.05, 0.08),
        "front_overhang": _u(rng, 0.13, 0.2),
        "rear_overhang": _u(rng, 0.13, 0.22),
        "spoiler": bool(kind in ("sedan", "coupe") and rng.random() < 0.3),
    }
    L, W, bh, wr = p["length"], p["width"], p["body_height"], p["wheel_radius"]
    base = wr * 0.6
    y0 = base + bh  # the body's top, the cabin's floor
    nose_y = base + p["nose_height"] * bh
    body = _extrude(
        [(-L / 2, base), (-L / 2, y0), (L / 2 - 0.05, y0 - 0.15 * bh), (L / 2, nose_y), (L / 2, base + 0.05 * bh)],
        W / 2,
    )
    # cabin: floor from the bonnet's end to the boot's start, roof shorter; the runs set the windscreen slope
    xf, xr = L / 2 - p["bonnet"] * L, -L / 2 + p["boot"] * L
    floor = xf - xr
    slopes = floor * (1 - p["roof_share"])
    run_rear = slopes * p["rear_slope_share"]
    run_front = slopes - run_rear
    ch = float(np.clip(run_front * math.tan(math.radians(p["windscreen_deg"])), 0.08, 0.24))
    p["cabin_height"] = ch
    y1, cw = y0 + ch, 0.9 * W
    glass_profile = [(xr, y0 - 0.01), (xf, y0 - 0.01), (xf - run_front, y1), (xr + run_rear, y1)]
    glass = _hull(
        [(x, y, sz * cw / 2) for x, y in glass_profile[:2] for sz in (-1, 1)]
        + [(x, y, sz * cw * 0.85 / 2) for x, y in glass_profile[2:] for sz in (-1, 1)]
    )
    # the roof: the glass house's top slab, a hair larger so that it covers the glass
    rt = 0.22 * ch
    yr = y1 - rt
    xfr, xrr = xf - run_front * (yr - y0) / ch, xr + run_rear * (yr - y0) / ch
    roof_w = cw * (0.85 + 0.15 * rt / ch) / 2 + 0.004
    roof = _hull(
        [(xfr + 0.004, yr, sz * roof_w) for sz in (-1, 1)]
        + [(xrr - 0.004, yr, sz * roof_w) for sz in (-1, 1)]
        + [(xf - run_front + 0.002, y1 + 0.004, sz * (cw * 0.85 / 2 + 0.004)) for sz in (-1, 1)]
        + [(xr + run_rear - 0.002, y1 + 0.004, sz * (cw * 0.85 / 2 + 0.004)) for sz in (-1, 1)]
    )
    wheels = [
        _cylinder(wr, p["wheel_width"], (x, wr, sz * (W / 2 - p["wheel_width"] / 3)), axis="z")
        for x in (L / 2 - p["front_overhang"], -L / 2 + p["rear_overhang"])
        for sz in (-1, 1)
    ]
    # lights and bumper stand a little proud of the front and rear faces
    lw, lh = 0.26 * W, 0.32 * (nose_y - base)
    head = [
        _box((0.03, lh, lw), (L / 2 - 0.008, nose_y - lh / 2 - 0.01, sz * (W / 2 - lw / 2 - 0.02))) for sz in (-1, 1)
    ]
    grille = _box((0.03, lh, W - 2 * lw - 0.1), (L / 2 - 0.008, nose_y - lh / 2 - 0.01, 0))
    bumper = _box((0.04, 0.3 * (nose_y - base), W * 0.96), (L / 2 - 0.005, base + 0.15 * (nose_y - base), 0))
    tw, th = 0.24 * W, 0.28 * bh
    tail = [
        _box((0.03, th, tw), (-L / 2 + 0.008, y0 - th / 2 - 0.015, sz * (W / 2 - tw / 2 - 0.015))) for sz in (-1, 1)
    ]

    color = _body_color(rng)
    body_texture = _texture(rng, 0.15, color)
    roof_color = color if rng.random() < 0.75 else _near(rng, (0.08, 0.08, 0.08) if rng.random() < 0.5 else (0.92,) * 3)
    parts: Groups = [
        ("body", [body], body_texture),
        ("glass", [glass], _solid(_near(rng, (0.16, 0.2, 0.27), 0.04))),
        ("roof", [roof], _solid(roof_color)),
        ("wheels", wheels, _solid(_near(rng, (0.09, 0.09, 0.1), 0.03))),
        ("head_lights", head, _solid(_near(rng, (1.0, 0.95, 0.72), 0.04))),
        ("front_bumper", [grille, bumper], _solid(_near(rng, (0.14, 0.14, 0.15), 0.04))),
        ("tail_lights", tail, _solid(_near(rng, (0.82, 0.05, 0.05), 0.05))),
    ]
    if p["spoiler"]:
        spoiler = [
            _box((0.08, 0.02, W * 0.9), (-L / 2 + 0.05, y0 + 0.06, 0)),
            _box((0.03, 0.06, 0.03), (-L / 2 + 0.05, y0 + 0.03, 0)),
        ]
        parts.append(("spoiler", spoiler, _solid(roof_color)))
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


def _airplane(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """An airliner or a light plane facing +X: a rounded nose with dark cockpit windows, a tail fin at the back."""
    p = {
        "length": _u(rng, 0.85, 1.0),
        "fuselage_radius": _u(rng, 0.03, 0.08),
        "span": _u(rng, 0.65, 1.1),
        "chord": _u(rng, 0.1, 0.26),
        "taper": _u(rng, 0.25, 0.85),
        "sweep_deg": _u(rng, 0, 40),
        "wing_x": _u(rng, -0.08, 0.12),
        "wing_y": _u(rng, -0.6, 0.6),  # low / mid / high wing, as a share of the fuselage radius
        "dihedral": _u(rng, -0.02, 0.07),
        "tail_span": _u(rng, 0.22, 0.42),
        "fin_height": _u(rng, 0.1, 0.22),
        "engines": int(rng.choice([0, 2, 2, 4])),
    }
    L, fr = p["length"], p["fuselage_radius"]
    # the tail cone: the fuselage narrows and rises towards the fin
    cabin = creation.capsule(height=0.75 * L - 2 * fr, radius=fr, count=[16, 16])
    cabin.apply_transform(rotation_matrix(math.pi / 2, [0, 1, 0]))
    cabin.apply_translation((0.125 * L, 0, 0))
    a = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    ring = np.stack([np.zeros_like(a), np.sin(a), np.cos(a)], axis=1)
    tail_cone = _hull(np.concatenate([ring * fr + [-0.125 * L, 0, 0], ring * fr * 0.35 + [-L / 2 + 0.01, 0.5 * fr, 0]]))
    x_nose = 0.5 * L
    cockpit = _hull(
        [
            (x_nose - 0.035 - 0.06 * k, fr * (0.55 + 0.3 * k), sz * fr * (0.5 + 0.25 * k))
            for k in (0, 1)
            for sz in (-1, 1)
        ]
        + [
            (x_nose - 0.06 - 0.06 * k, fr * (0.25 + 0.3 * k), sz * fr * (0.8 + 0.1 * k))
            for k in (0, 1)
            for sz in (-1, 1)
        ]
    )
    c = p["chord"]
    wy = p["wing_y"] * fr
    wings = [
        _wing(p["wing_x"], c, c * p["taper"], p["span"] / 2, p["sweep_deg"], 0.02, wy, s, p["dihedral"])
        for s in (-1, 1)
    ]
    tx = -L / 2 + 0.08
    tail = [_wing(tx, c * 0.6, c * 0.3, p["tail_span"] / 2, p["sweep_deg"], 0.015, fr * 0.4, s) for s in (-1, 1)]
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
    body_color = _palette_color(rng, saturation=(0.0, 0.25), value=(0.6, 0.85))  # liveries: light fuselages
    accent = _body_color(rng)
    parts: Groups = [
        ("fuselage", [cabin, tail_cone], _solid(body_color)),
        ("cockpit", [cockpit], _solid(_near(rng, (0.1, 0.12, 0.18), 0.04))),
        ("wings", wings, _texture(rng, 0.2, _contrasting(rng, body_color, 0.2, value=(0.35, 0.8)))),
        ("tail", tail + [fin], _solid(accent)),
    ]
    if p["engines"]:
        zs = [0.3] if p["engines"] == 2 else [0.22, 0.4]
        tan_sweep = math.tan(math.radians(p["sweep_deg"]))
        # under the wing, following its sweep
        engines = [
            _cylinder(
                fr * 0.6,
                c * 0.8,
                (p["wing_x"] + 0.1 * c - z * p["span"] / 2 * tan_sweep, wy - fr * 0.9, s * z * p["span"] / 2),
                axis="x",
                sections=14,
            )
            for z in zs
            for s in (-1, 1)
        ]
        parts.append(("engines", engines, _solid(accent)))
    return parts, p


def _lamp(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A desk lamp: the arm reaches forward (+X) from the stem and the shade hangs at its end."""
    p = {
        "base": str(rng.choice(["disc", "box"])),
        "base_radius": _u(rng, 0.12, 0.22),
        "stem_height": _u(rng, 0.45, 0.9),
        "stem_radius": _u(rng, 0.012, 0.028),
        "arm_length": _u(rng, 0.18, 0.4),
        "arm_rise_deg": _u(rng, -10, 35),
        "shade": str(rng.choice(["cone", "cone", "sphere", "cylinder"])),
        "shade_bottom": _u(rng, 0.12, 0.26),
        "shade_top": _u(rng, 0.04, 0.12),
        "shade_height": _u(rng, 0.12, 0.28),
        "shade_tilt_deg": _u(rng, 0, 35),
    }
    br, sh, sr = p["base_radius"], p["stem_height"], p["stem_radius"]
    base = (
        _cylinder(br, 0.04, (0, 0.02, 0), sections=28)
        if p["base"] == "disc"
        else _box((2 * br, 0.05, 2 * br * 0.8), (0, 0.025, 0))
    )
    # the stem stands at the back of the base
    sx = -0.5 * br
    stem = [_cylinder(sr, sh, (sx, sh / 2, 0))]
    al, rise = p["arm_length"], math.radians(p["arm_rise_deg"])
    arm = _cylinder(sr, al, (al / 2, 0, 0), axis="x")
    arm.apply_transform(rotation_matrix(rise, [0, 0, 1]))
    arm.apply_translation((sx, sh, 0))
    stem.append(arm)
    top = np.array([sx + al * math.cos(rise), sh + al * math.sin(rise), 0.0])
    hh = p["shade_height"]
    if p["shade"] == "sphere":
        shade = creation.icosphere(subdivisions=2, radius=p["shade_bottom"] * 0.7)
        shade.apply_translation([0, -p["shade_bottom"] * 0.3, 0])
    elif p["shade"] == "cylinder":
        shade = _cylinder(p["shade_bottom"] * 0.7, hh, (0, -hh * 0.3, 0), sections=28)
    else:
        shade = _frustum(p["shade_bottom"], p["shade_top"], hh, (0, -hh * 0.3, 0))
    shade.apply_transform(rotation_matrix(-math.radians(p["shade_tilt_deg"]), [0, 0, 1]))
    shade.apply_translation(top)
    switch = _box((0.05, 0.03, 0.05), (0.55 * br, 0.05, 0))
    shade_color = _body_color(rng)
    metal = _contrasting(rng, shade_color, 0.3)
    parts: Groups = [
        ("base", [base], _solid(metal)),
        ("stem", stem, _solid(metal)),
        ("shade", [shade], _texture(rng, 0.3, shade_color)),
        ("switch", [switch], _solid(_contrasting(rng, metal, 0.4))),
    ]
    return parts, p


def _mug(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A mug whose handle is its back (-X), in a colour that stands out from the cup's."""
    p = {
        "radius": _u(rng, 0.26, 0.46),
        "height": _u(rng, 0.55, 1.05),
        "taper": _u(rng, 0.8, 1.0),  # bottom radius over top radius
        "wall": _u(rng, 0.025, 0.05),
        "handle_radius": _u(rng, 0.14, 0.26),
        "handle_thickness": _u(rng, 0.025, 0.055),
        "handle_height": _u(rng, 0.4, 0.6),
    }
    r, h, wall = p["radius"], p["height"], p["wall"]
    rb = r * p["taper"]
    body = creation.annulus(r_min=r - wall, r_max=r, height=h, sections=40)
    body.apply_transform(rotation_matrix(-math.pi / 2, [1, 0, 0]))
    # taper: scale each ring's radius linearly from the bottom (y = 0) to the top (y = h)
    body.apply_translation((0, h / 2, 0))
    v = body.vertices.copy()
    v[:, [0, 2]] *= rb / r + (1 - rb / r) * v[:, 1:2] / h
    body.vertices = v
    bottom = _cylinder(rb - wall / 2, wall, (0, wall / 2, 0), sections=40)
    hr = p["handle_radius"] * h
    hy = p["handle_height"] * h
    r_at = rb + (r - rb) * hy / h
    handle = creation.torus(major_radius=hr, minor_radius=p["handle_thickness"], major_sections=32, minor_sections=12)
    handle.apply_translation((-r_at, hy, 0))
    # keep only the outer half of the ring: the inner half would poke into the cup
    outside = handle.vertices[handle.faces][:, :, 0].max(axis=1) < -(r_at - wall)
    handle.update_faces(outside)
    handle.remove_unreferenced_vertices()
    cup_color = _body_color(rng)
    parts: Groups = [
        ("body", [body, bottom], _texture(rng, 0.4, cup_color)),
        ("handle", [handle], _solid(_contrasting(rng, cup_color, 0.45))),
    ]
    return parts, p


#: category name -> (pseudo synset id, builder)
CATEGORIES: dict[str, tuple[str, Callable[[Rng], tuple[Groups, dict]]]] = {
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
        Part(name, trimesh.util.concatenate(meshes), texture if texture is not None else _texture(rng, patterned))
        for name, meshes, texture in groups
    ]
    params = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in params.items()}
    params["textures"] = {part.name: part.texture.to_json() for part in parts}
    return ProceduralObject(category, parts, params).normalise()
