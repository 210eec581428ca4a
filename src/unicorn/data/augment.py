"""Batch augmentation of training images, on whatever device the batch is on.

The image is both the encoder's input and the reconstruction target, so an augmentation changes what the model
must reconstruct, not only what it sees: a hue shift asks it for an object of another colour.
"""

from __future__ import annotations

import math

import torch
from kornia.enhance import adjust_hue

from unicorn.checks import check_shape

__all__ = ["random_hue_shift"]


def random_hue_shift(images: torch.Tensor, max_shift: float, generator: torch.Generator) -> torch.Tensor:
    """Rotate each image's hue by its own random fraction of the hue circle, uniform in ``[-max_shift, max_shift]``.

    Greys (white backgrounds, shading without colour) are unchanged; saturation and value are kept, so the result
    stays in [0, 1]. The draws come from ``generator`` (a CPU generator: the same shifts on every device).

    Args:
        images: (B, 3, H, W) RGB in [0, 1].
        max_shift: the largest shift as a fraction of the hue circle, in [0, 0.5] (0.5: any hue).
        generator: the random stream of the draws (B of them).

    Returns:
        (B, 3, H, W), ``images`` itself when ``max_shift`` is 0.
    """
    B = check_shape(images, "B, 3, H, W", "images")["B"]
    if not 0.0 <= max_shift <= 0.5:
        raise ValueError(f"max_shift must be in [0, 0.5] (a fraction of the hue circle), got {max_shift}")
    if max_shift == 0.0:
        return images
    fractions = (torch.rand(B, generator=generator, dtype=torch.float64) * 2 - 1) * max_shift
    angles = (fractions * 2 * math.pi).to(device=images.device, dtype=images.dtype)
    return adjust_hue(images, angles)
