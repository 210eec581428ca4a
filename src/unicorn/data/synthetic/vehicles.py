"""Synthetic vehicles: a car and an airplane.

Each builder maps a numpy generator to ``(parts, params)`` (:data:`~.primitives.Groups` and the sampled
proportions); every category has a front (+X) that its back does not look like, so that a view and the same view
turned by 180 degrees are different pictures.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import trimesh
from trimesh import creation
from trimesh.transformations import rotation_matrix

from unicorn.data.synthetic.primitives import (
    Groups,
    Rng,
    body_color,
    box,
    contrasting,
    cylinder,
    extrude,
    hull,
    near,
    palette_color,
    random_texture,
    solid,
    uniform,
)

__all__ = ["airplane", "car"]

#: car body types: (bonnet, boot) length ranges as shares of the length, body height, cabin height share,
#: windscreen angle from the horizontal (degrees), rear window's share of the cabin's slopes
_CAR_TYPES: dict[str, dict[str, tuple[float, float]]] = {
    "sedan": {"bonnet": (0.32, 0.4), "boot": (0.14, 0.2), "body": (0.13, 0.19), "windscreen": (25, 35)},
    "hatchback": {"bonnet": (0.26, 0.34), "boot": (0.03, 0.08), "body": (0.14, 0.2), "windscreen": (25, 38)},
    "suv": {"bonnet": (0.24, 0.3), "boot": (0.03, 0.07), "body": (0.2, 0.27), "windscreen": (32, 45)},
    "coupe": {"bonnet": (0.36, 0.44), "boot": (0.12, 0.18), "body": (0.11, 0.15), "windscreen": (20, 28)},
}


def car(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A car facing +X: a long bonnet and a short boot, a sloped windscreen, white head and red tail lights.

    The body is the side profile (low nose, bonnet sloping up to the windscreen, vertical tail) extruded
    across the width; the cabin is a glass house (dark glass) under a roof of the body colour. The front
    carries a dark bumper and grille between warm-white head lights, the tail red lights.
    """
    p = _car_proportions(rng)
    L, W, bh, wr = p["length"], p["width"], p["body_height"], p["wheel_radius"]
    base = wr * 0.6
    y0 = base + bh  # the body's top, the cabin's floor
    nose_y = base + p["nose_height"] * bh
    body = extrude(
        [(-L / 2, base), (-L / 2, y0), (L / 2 - 0.05, y0 - 0.15 * bh), (L / 2, nose_y), (L / 2, base + 0.05 * bh)],
        W / 2,
    )
    glass, roof = _car_cabin(p, y0)
    wheels = [
        cylinder(wr, p["wheel_width"], (x, wr, sz * (W / 2 - p["wheel_width"] / 3)), axis="z")
        for x in (L / 2 - p["front_overhang"], -L / 2 + p["rear_overhang"])
        for sz in (-1, 1)
    ]
    head, front, tail = _car_lights(p, base, y0, nose_y)

    color = body_color(rng)
    body_texture = random_texture(rng, 0.15, color)
    roof_color = color if rng.random() < 0.75 else near(rng, (0.08, 0.08, 0.08) if rng.random() < 0.5 else (0.92,) * 3)
    parts: Groups = [
        ("body", [body], body_texture),
        ("glass", [glass], solid(near(rng, (0.16, 0.2, 0.27), 0.04))),
        ("roof", [roof], solid(roof_color)),
        ("wheels", wheels, solid(near(rng, (0.09, 0.09, 0.1), 0.03))),
        ("head_lights", head, solid(near(rng, (1.0, 0.95, 0.72), 0.04))),
        ("front_bumper", front, solid(near(rng, (0.14, 0.14, 0.15), 0.04))),
        ("tail_lights", tail, solid(near(rng, (0.82, 0.05, 0.05), 0.05))),
    ]
    if p["spoiler"]:
        spoiler = [
            box((0.08, 0.02, W * 0.9), (-L / 2 + 0.05, y0 + 0.06, 0)),
            box((0.03, 0.06, 0.03), (-L / 2 + 0.05, y0 + 0.03, 0)),
        ]
        parts.append(("spoiler", spoiler, solid(roof_color)))
    return parts, p


def _car_proportions(rng: Rng) -> dict[str, Any]:
    """A car's body type and proportions (the length is 1)."""
    kind = str(rng.choice(list(_CAR_TYPES)))
    ranges = _CAR_TYPES[kind]
    return {
        "type": kind,
        "length": 1.0,
        "width": uniform(rng, 0.36, 0.5),
        "body_height": uniform(rng, *ranges["body"]),
        "bonnet": uniform(rng, *ranges["bonnet"]),
        "boot": uniform(rng, *ranges["boot"]),
        "nose_height": uniform(rng, 0.5, 0.8),  # share of the body height at the very front
        "windscreen_deg": uniform(rng, *ranges["windscreen"]),
        "roof_share": uniform(rng, 0.35, 0.6) if kind != "suv" else uniform(rng, 0.6, 0.75),
        "rear_slope_share": uniform(rng, 0.2, 0.45),  # of what the roof leaves, the rest is the windscreen's run
        "wheel_radius": uniform(rng, 0.065, 0.095) * (1.2 if kind == "suv" else 1.0),
        "wheel_width": uniform(rng, 0.05, 0.08),
        "front_overhang": uniform(rng, 0.13, 0.2),
        "rear_overhang": uniform(rng, 0.13, 0.22),
        "spoiler": bool(kind in ("sedan", "coupe") and rng.random() < 0.3),
    }


def _car_cabin(p: dict[str, Any], y0: float) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """The glass house on the body's top ``y0`` and the roof over it; records ``p["cabin_height"]``."""
    L, W = p["length"], p["width"]
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
    glass = hull(
        [(x, y, sz * cw / 2) for x, y in glass_profile[:2] for sz in (-1, 1)]
        + [(x, y, sz * cw * 0.85 / 2) for x, y in glass_profile[2:] for sz in (-1, 1)]
    )
    # the roof: the glass house's top slab, a hair larger so that it covers the glass
    rt = 0.22 * ch
    yr = y1 - rt
    xfr, xrr = xf - run_front * (yr - y0) / ch, xr + run_rear * (yr - y0) / ch
    roof_w = cw * (0.85 + 0.15 * rt / ch) / 2 + 0.004
    roof = hull(
        [(xfr + 0.004, yr, sz * roof_w) for sz in (-1, 1)]
        + [(xrr - 0.004, yr, sz * roof_w) for sz in (-1, 1)]
        + [(xf - run_front + 0.002, y1 + 0.004, sz * (cw * 0.85 / 2 + 0.004)) for sz in (-1, 1)]
        + [(xr + run_rear - 0.002, y1 + 0.004, sz * (cw * 0.85 / 2 + 0.004)) for sz in (-1, 1)]
    )
    return glass, roof


def _car_lights(
    p: dict[str, Any], base: float, y0: float, nose_y: float
) -> tuple[list[trimesh.Trimesh], list[trimesh.Trimesh], list[trimesh.Trimesh]]:
    """Head lights, the front (grille and bumper) and tail lights of a body from ``base`` to ``y0`` whose nose
    is ``nose_y`` high."""
    L, W, bh = p["length"], p["width"], p["body_height"]
    # lights and bumper stand a little proud of the front and rear faces
    lw, lh = 0.26 * W, 0.32 * (nose_y - base)
    head = [
        box((0.03, lh, lw), (L / 2 - 0.008, nose_y - lh / 2 - 0.01, sz * (W / 2 - lw / 2 - 0.02))) for sz in (-1, 1)
    ]
    grille = box((0.03, lh, W - 2 * lw - 0.1), (L / 2 - 0.008, nose_y - lh / 2 - 0.01, 0))
    bumper = box((0.04, 0.3 * (nose_y - base), W * 0.96), (L / 2 - 0.005, base + 0.15 * (nose_y - base), 0))
    tw, th = 0.24 * W, 0.28 * bh
    tail = [box((0.03, th, tw), (-L / 2 + 0.008, y0 - th / 2 - 0.015, sz * (W / 2 - tw / 2 - 0.015))) for sz in (-1, 1)]
    return head, [grille, bumper], tail


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
    return hull(pts)


def airplane(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """An airliner or a light plane facing +X: a rounded nose with dark cockpit windows, a tail fin at the back."""
    p = {
        "length": uniform(rng, 0.85, 1.0),
        "fuselage_radius": uniform(rng, 0.03, 0.08),
        "span": uniform(rng, 0.65, 1.1),
        "chord": uniform(rng, 0.1, 0.26),
        "taper": uniform(rng, 0.25, 0.85),
        "sweep_deg": uniform(rng, 0, 40),
        "wing_x": uniform(rng, -0.08, 0.12),
        "wing_y": uniform(rng, -0.6, 0.6),  # low / mid / high wing, as a share of the fuselage radius
        "dihedral": uniform(rng, -0.02, 0.07),
        "tail_span": uniform(rng, 0.22, 0.42),
        "fin_height": uniform(rng, 0.1, 0.22),
        "engines": int(rng.choice([0, 2, 2, 4])),
    }
    fuselage, cockpit = _fuselage(p["length"], p["fuselage_radius"])
    c, fr = p["chord"], p["fuselage_radius"]
    wy = p["wing_y"] * fr
    wings = [
        _wing(p["wing_x"], c, c * p["taper"], p["span"] / 2, p["sweep_deg"], 0.02, wy, s, p["dihedral"])
        for s in (-1, 1)
    ]
    livery = palette_color(rng, saturation=(0.0, 0.25), value=(0.6, 0.85))  # light fuselages
    accent = body_color(rng)
    parts: Groups = [
        ("fuselage", fuselage, solid(livery)),
        ("cockpit", [cockpit], solid(near(rng, (0.1, 0.12, 0.18), 0.04))),
        ("wings", wings, random_texture(rng, 0.2, contrasting(rng, livery, 0.2, value=(0.35, 0.8)))),
        ("tail", _tail(p), solid(accent)),
    ]
    if p["engines"]:
        zs = [0.3] if p["engines"] == 2 else [0.22, 0.4]
        tan_sweep = math.tan(math.radians(p["sweep_deg"]))
        # under the wing, following its sweep
        engines = [
            cylinder(
                fr * 0.6,
                c * 0.8,
                (p["wing_x"] + 0.1 * c - z * p["span"] / 2 * tan_sweep, wy - fr * 0.9, s * z * p["span"] / 2),
                axis="x",
                sections=14,
            )
            for z in zs
            for s in (-1, 1)
        ]
        parts.append(("engines", engines, solid(accent)))
    return parts, p


def _fuselage(L: float, fr: float) -> tuple[list[trimesh.Trimesh], trimesh.Trimesh]:
    """A fuselage of length ``L`` and radius ``fr`` (a capsule and its tail cone) and the cockpit windows."""
    cabin = creation.capsule(height=0.75 * L - 2 * fr, radius=fr, count=[16, 16])
    cabin.apply_transform(rotation_matrix(math.pi / 2, [0, 1, 0]))
    cabin.apply_translation((0.125 * L, 0, 0))
    # the tail cone: the fuselage narrows and rises towards the fin
    a = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    ring = np.stack([np.zeros_like(a), np.sin(a), np.cos(a)], axis=1)
    tail_cone = hull(np.concatenate([ring * fr + [-0.125 * L, 0, 0], ring * fr * 0.35 + [-L / 2 + 0.01, 0.5 * fr, 0]]))
    x_nose = 0.5 * L
    cockpit = hull(
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
    return [cabin, tail_cone], cockpit


def _tail(p: dict[str, Any]) -> list[trimesh.Trimesh]:
    """The tail planes and the fin of an airplane of proportions ``p``."""
    L, c, fr = p["length"], p["chord"], p["fuselage_radius"]
    tx = -L / 2 + 0.08
    tail = [_wing(tx, c * 0.6, c * 0.3, p["tail_span"] / 2, p["sweep_deg"], 0.015, fr * 0.4, s) for s in (-1, 1)]
    fh = p["fin_height"]
    fin = hull(
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
    return tail + [fin]
