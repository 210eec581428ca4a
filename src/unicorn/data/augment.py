"""Batch augmentation of training images, on whatever device the batch is on.

The image is both the encoder's input and the reconstruction target, so an augmentation changes what the model
must reconstruct, not only what it sees: a hue shift asks it for an object of another colour.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.enhance import adjust_hue

from unicorn.checks import check_shape
from unicorn.hostsync import draw_device

__all__ = ["random_hue_shift", "random_roll_shift", "roll_shift_images"]


def random_hue_shift(images: torch.Tensor, max_shift: float, generator: torch.Generator) -> torch.Tensor:
    """Rotate each image's hue by its own random fraction of the hue circle, uniform in ``[-max_shift, max_shift]``.

    Greys (white backgrounds, shading without colour) are unchanged; saturation and value are kept, so the result
    stays in [0, 1]. The draws come from ``generator``, on its device (a CPU generator: the same shifts on every
    device, copied to the images').

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
    draws = torch.rand(B, generator=generator, dtype=torch.float64, device=draw_device(images.device, generator))
    fractions = (draws * 2 - 1) * max_shift
    angles = (fractions * 2 * math.pi).to(device=images.device, dtype=images.dtype)
    return adjust_hue(images, angles)


def roll_shift_images(images: torch.Tensor, roll: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Each image turned about its centre by ``roll`` degrees and moved by ``shift``, in the camera's NDC
    (:mod:`unicorn.geometry.cameras`: +x image-left, +y image-up; the image spans [-1, 1]).

    A point at NDC ``q`` of an image lands at ``Rot(roll) @ q + shift`` of the result, ``Rot`` turning +x toward +y:
    the picture of the same scene taken by the camera rolled about its optical axis (exactly) and moved parallel
    to the image (to first order in the depth's spread). Pixels from outside the image mirror its border.

    Args:
        images: (B, C, H, W).
        roll: (B,) degrees.
        shift: (B, 2) NDC.

    Returns:
        (B, C, H, W).
    """
    B = check_shape(images, "B, C, H, W", "images")["B"]
    check_shape(roll, "B", "roll", {"B": B})
    check_shape(shift, "B, 2", "shift", {"B": B})
    r = torch.deg2rad(roll.to(images.device, torch.float32))
    c, s = r.cos(), r.sin()
    # the result's pixel at NDC p reads the input at Rot(-roll) @ (p - shift); grid_sample's coordinates are
    # the NDC's negated, and a rotation commutes with that negation
    inv = torch.stack([torch.stack([c, s], -1), torch.stack([-s, c], -1)], -2)  # (B, 2, 2): Rot(-roll)
    offset = inv @ shift.to(images.device, torch.float32).unsqueeze(-1)  # (B, 2, 1): Rot(-roll) @ shift, negated twice
    theta = torch.cat([inv, offset], -1)
    grid = F.affine_grid(theta, list(images.shape), align_corners=False)
    return F.grid_sample(images, grid.to(images.dtype), mode="bilinear", padding_mode="reflection", align_corners=False)


def random_roll_shift(
    images: torch.Tensor, max_roll: float, max_shift: float, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each image rolled and shifted (:func:`roll_shift_images`) by its own uniform draws in ``[-max_roll, max_roll]``
    degrees and ``[-max_shift, max_shift]`` NDC along x and y.

    Args:
        images: (B, C, H, W).
        max_roll: the largest roll, degrees, >= 0.
        max_shift: the largest shift along each axis, NDC, >= 0.
        generator: the generator of the draws, on its device (a CPU generator: the same draws on every device;
            None: torch's global one on the images' device; :func:`~unicorn.hostsync.draw_device`).

    Returns:
        the images (B, C, H, W), their rolls (B,) degrees and shifts (B, 2) NDC, on the images' device.
    """
    B = check_shape(images, "B, C, H, W", "images")["B"]
    if max_roll < 0 or max_shift < 0:
        raise ValueError(f"max_roll and max_shift must be >= 0, got {max_roll}, {max_shift}")
    draws = torch.rand(B, 3, generator=generator, device=draw_device(images.device, generator)) * 2 - 1
    roll = (draws[:, 0] * max_roll).to(images.device)
    shift = (draws[:, 1:] * max_shift).to(images.device)
    return roll_shift_images(images, roll, shift), roll, shift
