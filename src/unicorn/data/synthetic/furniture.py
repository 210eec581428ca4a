"""Synthetic furniture: a chair and a desk.

Each builder maps a numpy generator to ``(parts, params)`` (:data:`~.primitives.Groups` and the sampled
proportions); every category has a front (+X) that its back does not look like, so that a view and the same view
turned by 180 degrees are different pictures.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import trimesh
from trimesh.transformations import rotation_matrix

from unicorn.data.synthetic.primitives import (
    Groups,
    Rng,
    body_color,
    box,
    contrasting,
    cylinder,
    near,
    random_texture,
    solid,
    uniform,
)

__all__ = ["chair", "table"]


def chair(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    p = {
        "seat_width": uniform(rng, 0.38, 0.65),
        "seat_depth": uniform(rng, 0.38, 0.62),
        "seat_thickness": uniform(rng, 0.03, 0.1),
        "seat_height": uniform(rng, 0.32, 0.52),
        "back_height": uniform(rng, 0.3, 0.75),
        "back_thickness": uniform(rng, 0.03, 0.07),
        "back_tilt_deg": uniform(rng, 0, 18),
        "back_style": str(rng.choice(["solid", "solid", "slats", "frame"])),
        "leg_radius": uniform(rng, 0.015, 0.04),
        "legs": str(rng.choice(["four", "four", "four_square", "pedestal"])),
        "arms": bool(rng.random() < 0.3),
    }
    w, d, t, h = p["seat_width"], p["seat_depth"], p["seat_thickness"], p["seat_height"]
    seat = box((d, t, w), (0, h, 0))
    bh, bt = p["back_height"], p["back_thickness"]
    if p["back_style"] == "solid":
        back = [box((bt, bh, w), (0, bh / 2, 0))]
    else:  # two posts and a top rail, with vertical slats or nothing between them
        post = 0.06 * w + 0.02
        back = [box((bt, bh, post), (0, bh / 2, sz * (w - post) / 2)) for sz in (-1, 1)]
        back.append(box((bt, 0.22 * bh, w), (0, bh * 0.89, 0)))
        if p["back_style"] == "slats":
            n = 3 if w < 0.5 else 4
            back += [box((bt * 0.7, bh, 0.04), (0, bh / 2, z)) for z in np.linspace(-w / 2, w / 2, n + 2)[1:-1]]
    back = trimesh.util.concatenate(back)
    back.apply_transform(rotation_matrix(math.radians(p["back_tilt_deg"]), [0, 0, 1]))
    back.apply_translation((-d / 2 + bt / 2, h + t / 2, 0))
    r = p["leg_radius"]
    legs = []
    if p["legs"] == "pedestal":
        legs.append(cylinder(r * 1.5, h - 0.05, (0, (h - 0.05) / 2 + 0.05, 0)))
        for k in range(5):
            foot = box((0.3 * max(w, d), 0.04, 0.05), (0.15 * max(w, d), 0.03, 0))
            foot.apply_transform(rotation_matrix(2 * math.pi * k / 5, [0, 1, 0]))
            legs.append(foot)
    else:
        for sx in (-1, 1):
            for sz in (-1, 1):
                c = (sx * (d / 2 - r * 1.5), (h - t / 2) / 2, sz * (w / 2 - r * 1.5))
                legs.append(
                    box((2 * r, h - t / 2, 2 * r), c) if p["legs"] == "four_square" else cylinder(r, h - t / 2, c)
                )
    seat_color = body_color(rng)
    back_color = seat_color if rng.random() < 0.5 else contrasting(rng, seat_color, 0.3)
    parts: Groups = [("seat", [seat], random_texture(rng, 0.3, seat_color)), ("back", [back], solid(back_color))]
    parts.append(("legs", legs, None))
    if p["arms"]:
        arms = [box((d * 0.8, 0.04, 0.04), (0, h + 0.2, sz * (w / 2 - 0.02))) for sz in (-1, 1)]
        arms += [box((0.04, 0.2, 0.04), (d * 0.3, h + 0.1, sz * (w / 2 - 0.02))) for sz in (-1, 1)]
        parts.append(("arms", arms, None))
    return parts, p


def table(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A desk: drawers hang under the top at the front, a modesty panel closes the back between the legs."""
    p = {
        "length": uniform(rng, 0.8, 1.6),  # along z (the long side faces the front)
        "depth": uniform(rng, 0.45, 0.85),
        "thickness": uniform(rng, 0.03, 0.08),
        "height": uniform(rng, 0.45, 0.8),
        "leg_radius": uniform(rng, 0.02, 0.05),
        "legs": str(rng.choice(["round", "square"])),
        "drawers": int(rng.integers(1, 4)),
        "drawer_height": uniform(rng, 0.1, 0.2),
        "overhang": uniform(rng, 0.1, 0.25),  # the top reaches past the front legs by this share of the depth
        "panel_drop": uniform(rng, 0.4, 0.8),  # share of the leg height the back panel covers
        "shelf": bool(rng.random() < 0.3),
    }
    L, D, t, h, r = p["length"], p["depth"], p["thickness"], p["height"], p["leg_radius"]
    top = box((D, t, L), (0, h - t / 2, 0))
    legs = []
    xf, xb = D / 2 - p["overhang"] * D - r, -0.96 * (D / 2 - r)  # front and back leg positions
    for x in (xb, xf):
        for sz in (-1, 1):
            c = (x, (h - t) / 2, sz * 0.95 * (L / 2 - r))
            legs.append(cylinder(r, h - t, c) if p["legs"] == "round" else box((2 * r, h - t, 2 * r), c))
    drop = p["panel_drop"] * (h - t)
    panel = box((0.02, drop, 0.95 * L - 2 * r), (xb, h - t - drop / 2, 0))
    # drawers side by side under the front edge, each with a knob
    n, dh = p["drawers"], p["drawer_height"]
    dw = 0.9 * L / max(n, 2)
    drawers, knobs = [], []
    for k in range(n):
        z = (k - (n - 1) / 2) * dw
        drawers.append(box((0.6 * D, dh, 0.94 * dw), (D / 2 - 0.3 * D - 0.01, h - t - dh / 2, z)))
        knobs.append(box((0.03, 0.03, 0.08), (D / 2 - 0.005, h - t - dh / 2, z)))
    top_color = body_color(rng)
    leg_color = contrasting(rng, top_color, 0.3)
    drawer_color = contrasting(rng, top_color, 0.35)
    parts: Groups = [
        ("top", [top], random_texture(rng, 0.3, top_color)),
        ("legs", legs + [panel], solid(leg_color)),
        ("drawers", drawers, solid(drawer_color)),
        ("knobs", knobs, solid(near(rng, (0.1, 0.1, 0.1)))),
    ]
    if p["shelf"]:
        parts.append(("shelf", [box((0.8 * D, 0.03, 0.85 * L), (0, h * 0.2, 0))], solid(leg_color)))
    return parts, p
