"""Batch augmentation: the hue shift against a per-pixel HSV computation (colorsys); the roll and shift against
an analytic blob and against rendering with the camera rolled and moved."""

from __future__ import annotations

import colorsys
import math

import pytest
import torch

from unicorn.data.augment import random_hue_shift, random_roll_shift, roll_shift_images
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.geometry.mesh import ellipsoid
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.render import TexturesVertex, build_renderer


def _shift_pixelwise(image: torch.Tensor, fraction: float) -> torch.Tensor:
    """(3, H, W) with every pixel's hue moved by ``fraction`` of the circle, one pixel at a time."""
    out = torch.empty_like(image)
    for i in range(image.shape[1]):
        for j in range(image.shape[2]):
            h, s, v = colorsys.rgb_to_hsv(*image[:, i, j].tolist())
            out[:, i, j] = torch.tensor(colorsys.hsv_to_rgb((h + fraction) % 1.0, s, v))
    return out


def test_each_image_gets_its_own_shift_within_range():
    images = torch.rand(6, 3, 5, 4, dtype=torch.float64)
    max_shift = 0.3
    shifted = random_hue_shift(images, max_shift, torch.Generator().manual_seed(7))
    # the draws: the same stream, as the function documents (uniform in [-max_shift, max_shift])
    fractions = (torch.rand(6, generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 2 - 1) * max_shift
    assert fractions.abs().max() <= max_shift and len(set(fractions.tolist())) == 6
    for b in range(6):
        torch.testing.assert_close(shifted[b], _shift_pixelwise(images[b], float(fractions[b])), atol=1e-6, rtol=0)
    assert shifted.min() >= 0 and shifted.max() <= 1


def test_greys_are_unchanged_and_zero_is_identity():
    grey = torch.rand(3, 1, 4, 4).expand(3, 3, 4, 4).contiguous()  # white, black and shades of grey
    torch.testing.assert_close(random_hue_shift(grey, 0.5, torch.Generator().manual_seed(0)), grey, atol=1e-6, rtol=0)
    images = torch.rand(2, 3, 4, 4)
    assert random_hue_shift(images, 0.0, torch.Generator().manual_seed(0)) is images


def test_same_generator_same_shifts():
    images = torch.rand(4, 3, 4, 4)
    a = random_hue_shift(images, 0.5, torch.Generator().manual_seed(3))
    b = random_hue_shift(images, 0.5, torch.Generator().manual_seed(3))
    c = random_hue_shift(images, 0.5, torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.allclose(a, c)


@pytest.mark.parametrize("max_shift", [-0.1, 0.6])
def test_shift_out_of_range_is_an_error(max_shift):
    with pytest.raises(ValueError, match="max_shift must be in"):
        random_hue_shift(torch.rand(1, 3, 2, 2), max_shift, torch.Generator())


def test_images_must_be_rgb_batches():
    with pytest.raises(ValueError, match="images"):
        random_hue_shift(torch.rand(3, 2, 2), 0.5, torch.Generator())


def _blob(size: int, centre: tuple[float, float], sigma: float = 0.25) -> torch.Tensor:
    """(1, 1, size, size): a Gaussian at ``centre`` in the camera's NDC (+x image-left, +y image-up)."""
    ndc = (size - 1 - 2 * torch.arange(size, dtype=torch.float64)) / size
    y, x = ndc.view(-1, 1), ndc.view(1, -1)  # rows go down the image (+y up), columns right (+x left)
    return torch.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / sigma**2).view(1, 1, size, size)


@pytest.mark.parametrize(
    "roll, shift", [(0.0, (0.2, 0.0)), (0.0, (0.0, -0.15)), (30.0, (0.0, 0.0)), (-20.0, (0.1, 0.1))]
)
def test_roll_shift_moves_a_point_to_rot_q_plus_shift(roll, shift):
    q = torch.tensor([0.3, -0.1], dtype=torch.float64)
    r = math.radians(roll)
    rot = torch.tensor([[math.cos(r), -math.sin(r)], [math.sin(r), math.cos(r)]], dtype=torch.float64)
    p = rot @ q + torch.tensor(shift, dtype=torch.float64)  # +x turns toward +y
    moved = roll_shift_images(_blob(64, tuple(q.tolist())), torch.tensor([roll]), torch.tensor([shift]))
    torch.testing.assert_close(moved.double(), _blob(64, tuple(p.tolist())), atol=0.02, rtol=0)


def test_roll_shift_is_the_rolled_and_moved_camera():
    """The picture of a mesh, rolled and shifted, against rendering it with the camera rolled by as much about
    its optical axis and the translation turned and moved by ``shift * T_z / f``."""
    size, focal = 64, 1 / math.tan(math.radians(15))
    verts, faces = ellipsoid(2, (1.0, 0.5, 0.3), 0.6)
    colors = ((verts / 0.6) * 0.5 + 0.5).clamp(0, 1)
    renderer = build_renderer(
        "layered", image_size=size, sigma=1e-4, faces_per_pixel=10, camera=PerspectiveCamera(fov=30)
    )

    def render(roll: float, T: list[float]) -> torch.Tensor:
        R = azim_elev_roll_to_rotation(torch.tensor([40.0]), torch.tensor([15.0]), torch.tensor([roll]))
        with torch.no_grad():
            out = renderer(verts[None], faces, TexturesVertex(colors[None]), R=R, T=torch.tensor([T]))
        return out[:, :3]

    T = [0.1, -0.05, 2.732]
    image = render(5.0, T)
    for roll, shift in [(12.0, (0.0, 0.0)), (0.0, (0.1, -0.05)), (-10.0, (0.08, 0.06))]:
        r = math.radians(roll)
        x = math.cos(r) * T[0] - math.sin(r) * T[1] + shift[0] * T[2] / focal
        y = math.sin(r) * T[0] + math.cos(r) * T[1] + shift[1] * T[2] / focal
        expected = render(5.0 + roll, [x, y, T[2]])
        moved = roll_shift_images(image, torch.tensor([roll]), torch.tensor([shift]))
        wrong = roll_shift_images(image, torch.tensor([-roll]), -torch.tensor([shift]))
        err, wrong_err = float((moved - expected).abs().mean()), float((wrong - expected).abs().mean())
        assert err < 0.01 and err < 0.25 * wrong_err, (roll, shift, err, wrong_err)


def test_no_roll_no_shift_is_identity():
    images = torch.rand(3, 3, 8, 8)
    torch.testing.assert_close(roll_shift_images(images, torch.zeros(3), torch.zeros(3, 2)), images)


def test_random_roll_shift_draws_each_image_its_own_within_range():
    images = torch.rand(5, 3, 8, 8)
    moved, roll, shift = random_roll_shift(images, 15.0, 0.1, torch.Generator().manual_seed(2))
    assert roll.shape == (5,) and shift.shape == (5, 2)
    assert roll.abs().max() <= 15 and shift.abs().max() <= 0.1 and len(set(roll.tolist())) == 5
    torch.testing.assert_close(moved, roll_shift_images(images, roll, shift))
    again = random_roll_shift(images, 15.0, 0.1, torch.Generator().manual_seed(2))
    assert all(torch.equal(a, b) for a, b in zip((moved, roll, shift), again, strict=True))
    with pytest.raises(ValueError, match="max_roll and max_shift must be >= 0"):
        random_roll_shift(images, -1.0, 0.1)
