"""Look-at cameras at the poles (straight above or below the target), where the world up is the viewing direction."""

import math

import pytest
import torch

from unicorn.geometry.rotations import (
    azim_elev_roll_to_rotation,
    camera_position_from_spherical,
    look_at_rotation,
    look_at_view_parameters,
    look_at_view_transform,
)

DTYPES = [torch.float32, torch.float64]


def _assert_rotations(R: torch.Tensor) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-6)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=1e-6)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("elev", [90.0, -90.0])
def test_a_camera_straight_above_or_below_is_the_limit_of_the_cameras_beside_the_pole(dtype, elev):
    azim = torch.tensor([0.0, 45.0, 200.0], dtype=dtype)
    R, T = look_at_view_transform(2.0, torch.tensor(elev, dtype=dtype), azim)
    _assert_rotations(R)
    # the same view as a camera a hundredth of a degree towards the equator: it turns with the azimuth
    inside = elev - 0.01 if elev > 0 else elev + 0.01
    R_inside, _ = look_at_view_transform(2.0, torch.tensor(inside, dtype=dtype), azim)
    assert torch.allclose(R, R_inside, atol=3e-4)
    # the camera looks at the origin from (0, +-2, 0)
    assert torch.allclose(R[:, :, 2], torch.tensor([0.0, -elev / 90.0, 0.0], dtype=dtype).expand(3, 3), atol=1e-6)
    assert torch.allclose(T, torch.tensor([0.0, 0.0, 2.0], dtype=dtype).expand(3, 3), atol=1e-6)


@pytest.mark.parametrize(
    "position, up",
    [([0.0, 2.0, 0.0], None), ([0.0, -3.0, 0.0], None), ([5.0, 0.0, 0.0], [1.0, 0.0, 0.0])],
    ids=["above", "below", "along-x"],
)
@pytest.mark.parametrize("dtype", DTYPES)
def test_a_camera_looking_along_up_gets_a_rotation(position, up, dtype):
    position = torch.tensor([position], dtype=dtype)
    R = look_at_rotation(position, up=None if up is None else torch.tensor([up], dtype=dtype))
    _assert_rotations(R)
    assert torch.allclose(R[0, :, 2], -position[0] / position[0].norm())  # still looking at the origin


@pytest.mark.parametrize("dtype", DTYPES)
def test_look_at_view_parameters_give_the_camera_back_at_and_beside_the_poles(dtype):
    elev = torch.tensor([90.0, -90.0, 89.99, -89.99, 0.0, 120.0, -179.9], dtype=dtype)
    azim = torch.tensor([45.0, 100.0, 170.0, -30.0, 10.0, 33.0, 90.0], dtype=dtype)
    R, T = look_at_view_transform(2.0, elev, azim)
    p = look_at_view_parameters(R, T)
    # with the up they give, and without it (+Y): the cameras have no roll
    atol = 1e-6 if dtype == torch.float32 else 1e-12
    for up in (p["up"], None):
        R2, T2 = look_at_view_transform(p["dist"], p["elev"], p["azim"], p["at"], up)
        _assert_rotations(R2)
        assert torch.allclose(R2, R, atol=atol)
        assert torch.allclose(T2, T, atol=atol)
    # straight above or below, azimuth and roll are one turn: any camera there is one without roll
    turned = R[:2] @ torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
    p = look_at_view_parameters(turned, T[:2])
    assert torch.allclose(look_at_view_transform(p["dist"], p["elev"], p["azim"])[0], turned, atol=1e-6)


def test_numbers_beside_float64_tensors_keep_float64():
    """A Python number takes the dtype of the tensors given with it, not float32 (which rounds a float64 camera's
    angles): the camera centre against its closed form in float64."""
    R, T = look_at_view_transform(torch.tensor(2.0, dtype=torch.float64), 30.0, 45.0)
    assert R.dtype == T.dtype == torch.float64
    e, a = math.radians(30.0), math.radians(45.0)
    want = [2 * math.cos(e) * math.sin(a), 2 * math.sin(e), 2 * math.cos(e) * math.cos(a)]
    centre = -(T.unsqueeze(1) @ R.transpose(1, 2)).squeeze(1)
    torch.testing.assert_close(centre[0], torch.tensor(want, dtype=torch.float64), rtol=0, atol=1e-15)
    # a float32 and a float64 tensor: float64, as torch's arithmetic promotes them
    azim, elev = torch.tensor([30.0, -120.0]), torch.tensor([10.0, 70.0], dtype=torch.float64)
    R = azim_elev_roll_to_rotation(azim, elev, torch.tensor(5.0, dtype=torch.float64))
    assert torch.equal(R, azim_elev_roll_to_rotation(azim.double(), elev, torch.tensor(5.0, dtype=torch.float64)))


def test_numbers_beside_a_batch_on_another_device_go_there():
    """The ``meta`` device stands in for CUDA: numbers and a batch of angles there broadcast together."""
    azim = torch.tensor([10.0, 20.0], device="meta")
    assert camera_position_from_spherical(2.0, 30.0, azim).device.type == "meta"
    assert azim_elev_roll_to_rotation(azim, 30.0, 5.0).device.type == "meta"


def test_one_up_or_target_serves_a_batch_and_a_batch_of_them_one_camera():
    # the oracle: each camera computed by itself
    ups = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0]])
    R, T = look_at_view_transform(2.5, 30.0, 45.0, up=ups)
    alone = [look_at_view_transform(2.5, 30.0, 45.0, up=u[None]) for u in ups]
    assert torch.equal(R, torch.cat([r for r, _ in alone])) and torch.equal(T, torch.cat([t for _, t in alone]))
    _assert_rotations(R)
    position = camera_position_from_spherical(2.5, 30.0, 45.0)[None]
    assert torch.equal(look_at_rotation(position, up=ups), R)
    # one up for three cameras, a target each
    at = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, -0.2, 0.3]])
    R, T = look_at_view_transform(2.0, torch.tensor([10.0, 20.0, 30.0]), 0.0, at=at, up=[0.0, 1.0, 0.0])
    for i in range(3):
        Ri, Ti = look_at_view_transform(2.0, 10.0 * (i + 1), 0.0, at=at[i : i + 1], up=[0.0, 1.0, 0.0])
        assert torch.equal(R[i : i + 1], Ri) and torch.equal(T[i : i + 1], Ti)


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: look_at_view_transform(2.0, 0.0, torch.tensor([0.0, 90.0, 180.0]), at=torch.zeros(2, 3)),
            r"^look_at_view_transform: 3 cameras \(dist, elev, azim\), 2 at points; each number must be 1 or the same",
        ),
        (
            lambda: look_at_view_transform(2.0, 0.0, 0.0, at=torch.zeros(2, 3), up=torch.ones(3, 3)),
            r"^look_at_view_transform: 1 cameras .*, 2 at points, 3 up directions; each number must be 1",
        ),
        (
            lambda: look_at_rotation(torch.ones(3, 3), up=torch.ones(2, 3)),
            r"^look_at: camera_position \(3, 3\), at \(3, 3\) and up \(2, 3\) do not broadcast together$",
        ),
    ],
    ids=["cameras-at", "at-up", "rotation"],
)
def test_batches_of_different_sizes_are_refused_in_one_line(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: look_at_rotation(torch.tensor([[0.0, 0.0, 2.0]]), up=torch.zeros(1, 3)),
            r"^look_at: an up vector is \(0, 0, 0\), which gives no direction$",
        ),
        (
            lambda: look_at_view_transform(
                2.0, 30.0, torch.tensor([0.0, 90.0]), up=[[0.0, 1.0, 0.0], [0.0, -0.0, 0.0]]
            ),
            r"^look_at: an up vector is \(0, 0, 0\)",
        ),
        (
            lambda: look_at_rotation(torch.tensor([[0.0, math.nan, 2.0]])),
            r"^look_at: camera_position, at or up contains NaN or infinite values$",
        ),
        (
            lambda: look_at_rotation(torch.tensor([[0.0, 0.0, 2.0]]), at=torch.tensor([math.inf, 0.0, 0.0])),
            "NaN or inf",
        ),
        (
            lambda: look_at_rotation(torch.tensor([[0.0, 0.0, 2.0]]), up=torch.tensor([0.0, math.nan, 0.0])),
            "NaN or inf",
        ),
        (lambda: look_at_view_transform(math.nan, 30.0, 45.0), "NaN or infinite"),
        (lambda: look_at_view_transform(2.0, 30.0, torch.tensor([45.0, math.inf])), "NaN or infinite"),
    ],
    ids=["zero-up", "zero-up-in-batch", "nan-position", "inf-at", "nan-up", "nan-dist", "inf-azim"],
)
def test_a_camera_with_no_up_direction_or_no_finite_position_is_refused(call, match):
    # a zero up gave an arbitrary camera (x axis picked as when looking along up), NaN gave NaN R and T
    with pytest.raises(ValueError, match=match):
        call()


def test_the_two_azimuth_conventions_place_the_camera_where_the_docs_say():
    # the camera centre -T @ R^T of each convention, against the directions the docstrings and docs/renderer.md give
    azim, elev = torch.tensor([0.0, 90.0, 0.0]), torch.tensor([0.0, 0.0, 30.0])
    dist = 2.0
    R, T = look_at_view_transform(dist, elev, azim)
    look_at_centre = -(T.unsqueeze(1) @ R.transpose(1, 2)).squeeze(1)
    R_pose = azim_elev_roll_to_rotation(azim, elev)
    pose_centre = -(torch.tensor([0.0, 0.0, dist]) @ R_pose.transpose(1, 2))
    h, v = dist * math.cos(math.radians(30.0)), dist * math.sin(math.radians(30.0))
    expected = torch.tensor([[0.0, 0.0, dist], [dist, 0.0, 0.0], [0.0, v, h]])  # +Z, +X, above +Z
    assert torch.allclose(look_at_centre, expected, atol=1e-5)
    assert torch.allclose(pose_centre, expected * torch.tensor([-1.0, 1.0, -1.0]), atol=1e-5)  # -Z, -X, above -Z
    assert torch.equal(R_pose[0], torch.eye(3))
