"""Synthetic household objects: a desk lamp and a mug.

Each builder maps a numpy generator to ``(parts, params)`` (:data:`~.primitives.Groups` and the sampled
proportions); every category has a front (+X) that its back does not look like, so that a view and the same view
turned by 180 degrees are different pictures.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from trimesh import creation
from trimesh.transformations import rotation_matrix

from unicorn.data.synthetic.primitives import (
    Groups,
    Rng,
    body_color,
    box,
    contrasting,
    cylinder,
    frustum,
    random_texture,
    solid,
    uniform,
)

__all__ = ["lamp", "mug"]


def lamp(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A desk lamp: the arm reaches forward (+X) from the stem and the shade hangs at its end."""
    p = {
        "base": str(rng.choice(["disc", "box"])),
        "base_radius": uniform(rng, 0.12, 0.22),
        "stem_height": uniform(rng, 0.45, 0.9),
        "stem_radius": uniform(rng, 0.012, 0.028),
        "arm_length": uniform(rng, 0.18, 0.4),
        "arm_rise_deg": uniform(rng, -10, 35),
        "shade": str(rng.choice(["cone", "cone", "sphere", "cylinder"])),
        "shade_bottom": uniform(rng, 0.12, 0.26),
        "shade_top": uniform(rng, 0.04, 0.12),
        "shade_height": uniform(rng, 0.12, 0.28),
        "shade_tilt_deg": uniform(rng, 0, 35),
    }
    br, sh, sr = p["base_radius"], p["stem_height"], p["stem_radius"]
    base = (
        cylinder(br, 0.04, (0, 0.02, 0), sections=28)
        if p["base"] == "disc"
        else box((2 * br, 0.05, 2 * br * 0.8), (0, 0.025, 0))
    )
    # the stem stands at the back of the base
    sx = -0.5 * br
    stem = [cylinder(sr, sh, (sx, sh / 2, 0))]
    al, rise = p["arm_length"], math.radians(p["arm_rise_deg"])
    arm = cylinder(sr, al, (al / 2, 0, 0), axis="x")
    arm.apply_transform(rotation_matrix(rise, [0, 0, 1]))
    arm.apply_translation((sx, sh, 0))
    stem.append(arm)
    top = np.array([sx + al * math.cos(rise), sh + al * math.sin(rise), 0.0])
    hh = p["shade_height"]
    if p["shade"] == "sphere":
        shade = creation.icosphere(subdivisions=2, radius=p["shade_bottom"] * 0.7)
        shade.apply_translation([0, -p["shade_bottom"] * 0.3, 0])
    elif p["shade"] == "cylinder":
        shade = cylinder(p["shade_bottom"] * 0.7, hh, (0, -hh * 0.3, 0), sections=28)
    else:
        shade = frustum(p["shade_bottom"], p["shade_top"], hh, (0, -hh * 0.3, 0))
    shade.apply_transform(rotation_matrix(-math.radians(p["shade_tilt_deg"]), [0, 0, 1]))
    shade.apply_translation(top)
    switch = box((0.05, 0.03, 0.05), (0.55 * br, 0.05, 0))
    shade_color = body_color(rng)
    metal = contrasting(rng, shade_color, 0.3)
    parts: Groups = [
        ("base", [base], solid(metal)),
        ("stem", stem, solid(metal)),
        ("shade", [shade], random_texture(rng, 0.3, shade_color)),
        ("switch", [switch], solid(contrasting(rng, metal, 0.4))),
    ]
    return parts, p


def mug(rng: Rng) -> tuple[Groups, dict[str, Any]]:
    """A mug whose handle is its back (-X), in a colour that stands out from the cup's."""
    p = {
        "radius": uniform(rng, 0.26, 0.46),
        "height": uniform(rng, 0.55, 1.05),
        "taper": uniform(rng, 0.8, 1.0),  # bottom radius over top radius
        "wall": uniform(rng, 0.025, 0.05),
        "handle_radius": uniform(rng, 0.14, 0.26),
        "handle_thickness": uniform(rng, 0.025, 0.055),
        "handle_height": uniform(rng, 0.4, 0.6),
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
    bottom = cylinder(rb - wall / 2, wall, (0, wall / 2, 0), sections=40)
    hr = p["handle_radius"] * h
    hy = p["handle_height"] * h
    r_at = rb + (r - rb) * hy / h
    handle = creation.torus(major_radius=hr, minor_radius=p["handle_thickness"], major_sections=32, minor_sections=12)
    handle.apply_translation((-r_at, hy, 0))
    # keep only the outer half of the ring: the inner half would poke into the cup
    outside = handle.vertices[handle.faces][:, :, 0].max(axis=1) < -(r_at - wall)
    handle.update_faces(outside)
    handle.remove_unreferenced_vertices()
    cup_color = body_color(rng)
    parts: Groups = [
        ("body", [body, bottom], random_texture(rng, 0.4, cup_color)),
        ("handle", [handle], solid(contrasting(rng, cup_color, 0.45))),
    ]
    return parts, p
