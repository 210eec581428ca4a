"""Helpers for the model tests: tiny configurations and a synthetic image set."""

from __future__ import annotations

import torch

from unicorn.config import model_preset
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.geometry.mesh import ellipsoid
from unicorn.geometry.rotations import look_at_view_transform
from unicorn.render import TexturesVertex, build_renderer

IMAGE_SIZE = 32


def tiny_config(family: str = "real", size: str = "small", **overrides):
    """A reference configuration shrunk for CPU tests (32 px images, 16 px textures, no VGG)."""
    base = {
        "image_size": IMAGE_SIZE,
        "texture": {"size": 16},
        "loss": {"perceptual": "structural", "perceptual_weight": 1.0},
    }
    for group, value in overrides.items():
        if isinstance(value, dict) and isinstance(base.get(group), dict):
            base[group] = {**base[group], **value}
        else:
            base[group] = value
    return model_preset(family, size, **base)


def randomize_heads(model: torch.nn.Module, std: float = 0.05, seed: int = 123) -> None:
    """Give every zero-initialised linear layer small random weights (so that all branches are live)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.Linear) and module.weight.abs().sum() == 0:
                module.weight.copy_(torch.randn(module.weight.shape, generator=g) * std)
                module.bias.copy_(torch.randn(module.bias.shape, generator=g) * std)


def ellipsoid_images(n: int = 8, size: int = IMAGE_SIZE) -> torch.Tensor:
    """Renders (n, 3, size, size) of a vertex-coloured ellipsoid from evenly spaced azimuths, on white."""
    verts, faces = ellipsoid(2, (1.0, 0.7, 0.7), 0.6)
    colors = ((verts / 0.6) * 0.5 + 0.5).clamp(0, 1)  # colour = direction: views are distinguishable
    renderer = build_renderer(
        "layered", image_size=size, sigma=1e-4, faces_per_pixel=10, camera=PerspectiveCamera(fov=30.0)
    )
    R, T = look_at_view_transform(dist=2.732, elev=10.0, azim=torch.linspace(0, 360, n + 1)[:n])
    with torch.no_grad():
        out = renderer(verts.expand(n, -1, -1), faces, TexturesVertex(colors.expand(n, -1, -1)), R=R, T=T)
    return out[:, :3].contiguous()
