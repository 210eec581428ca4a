import math

import numpy as np
import pytest
import torch

from unicorn.geometry.cameras import PerspectiveCamera, ndc_to_pixel, opencv_camera, pixel_to_ndc, world_to_view
from unicorn.geometry.rotations import (
    azim_elev_roll_to_rotation,
    camera_position_from_spherical,
    euler_angles_to_matrix,
    look_at_view_transform,
    rotation_angle_between,
)


def test_fov_and_focal_length_agree():
    cam = PerspectiveCamera(fov=30.0)
    assert float(cam.focal_length) == pytest.approx(1 / math.tan(math.radians(15)))
    assert PerspectiveCamera(focal_length=3.732050895690918).fov == pytest.approx(30.0)


def test_one_element_tensors_and_numpy_scalars_are_numbers():
    for fov in (torch.tensor(30.0), torch.tensor([30]), np.float32(30.0), np.int64(30)):
        assert PerspectiveCamera(fov=fov).fov == pytest.approx(30.0)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({}, "give exactly one of fov"),
        ({"fov": 30.0, "focal_length": 2.0}, "give exactly one of fov"),
        ({"fov": 0.0}, r"fov must be in \(0, 180\) degrees, got 0.0"),
        ({"focal_length": -1.0}, "focal_length must be a finite number > 0, got -1.0"),
    ],
)
def test_bad_camera_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PerspectiveCamera(**kwargs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
def test_a_projection_is_exact_to_the_points_dtype(dtype):
    point = torch.tensor([[0.123456789, -0.3, 2.7182818]], dtype=torch.float64)
    exact = point[:, :2] / math.tan(math.radians(30.0) / 2.0) / point[:, 2:]  # float64 throughout
    for cam in (PerspectiveCamera(fov=30.0), PerspectiveCamera(fov=30.0).float().to(dtype)):
        got = cam.project(point.to(dtype))
        assert got.dtype == dtype
        assert torch.allclose(got[:, :2].double(), exact, rtol=torch.finfo(dtype).eps * 4, atol=0)


def test_pixel_centres_follow_pytorch3d_convention():
    # square image: centre of pixel (row i, col j) at (1 - (2j+1)/W, 1 - (2i+1)/H)
    H = W = 8
    cols, rows = torch.meshgrid(torch.arange(W.__float__()), torch.arange(H.__float__()), indexing="xy")
    ndc = pixel_to_ndc(torch.stack([cols, rows], -1), (H, W))
    assert torch.allclose(ndc[..., 0], 1 - (2 * cols + 1) / W)
    assert torch.allclose(ndc[..., 1], 1 - (2 * rows + 1) / H)
    assert torch.allclose(ndc_to_pixel(ndc, (H, W)), torch.stack([cols, rows], -1))
    # non-square: the short side spans [-1, 1]
    ndc = pixel_to_ndc(torch.tensor([[0.0, 0.0], [15.0, 7.0]]), (8, 16))
    assert torch.allclose(ndc, torch.tensor([[15 / 8, 7 / 8], [-15 / 8, -7 / 8]]))


def test_projection_left_up_forward():
    cam = PerspectiveCamera(fov=90.0)
    pts = torch.tensor([[[1.0, 0.0, 2.0], [0.0, 1.0, 4.0]]])
    ndc = cam.project(pts)
    assert torch.allclose(ndc, torch.tensor([[[0.5, 0.0, 2.0], [0.0, 0.25, 4.0]]]))
    # +X in view space is image-left: a point with x > 0 lands in a column left of the centre
    screen = cam.transform_points_screen(pts, torch.eye(3)[None], torch.zeros(1, 3), 64)
    assert screen[0, 0, 0] < 31.5 and screen[0, 1, 1] < 31.5


def test_look_at_puts_target_on_axis_and_camera_at_origin():
    R, T = look_at_view_transform(
        dist=torch.tensor([2.0, 3.0]), elev=torch.tensor([30.0, -20.0]), azim=torch.tensor([45.0, 200.0])
    )
    eye = camera_position_from_spherical(
        torch.tensor([2.0, 3.0]), torch.tensor([30.0, -20.0]), torch.tensor([45.0, 200.0])
    )
    assert torch.allclose(world_to_view(eye[:, None], R, T), torch.zeros(2, 1, 3), atol=1e-5)
    origin = world_to_view(torch.zeros(2, 1, 3), R, T)[:, 0]
    assert torch.allclose(origin, torch.tensor([[0, 0, 2.0], [0, 0, 3.0]]), atol=1e-5)
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3).expand(2, 3, 3), atol=1e-6)
    assert torch.allclose(torch.linalg.det(R), torch.ones(2), atol=1e-6)
    # world up stays image up
    up = world_to_view(torch.tensor([[[0.0, 0.1, 0.0]]]).expand(2, 1, 3), R, T)[:, 0] - origin
    assert (up[:, 1] > 0).all()


def test_look_at_takes_pytorch3d_style_lists_and_a_shifted_target():
    at, up = ((0.2, 0.1, -0.3),), ((0.0, 1.0, 0.0),)
    R, T = look_at_view_transform(2.0, 30.0, 45.0, at=at, up=up)
    assert torch.allclose(R, look_at_view_transform(2.0, 30.0, 45.0, at=torch.tensor(at))[0])
    # the target lies on the optical axis at the camera's distance
    assert torch.allclose(world_to_view(torch.tensor(at)[None], R, T), torch.tensor([[[0.0, 0.0, 2.0]]]), atol=1e-5)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"dist": 0.0}, r"a camera is at the point it looks at"),
        ({"dist": torch.tensor([2.0, 0.0])}, r"a camera is at the point it looks at"),
        ({"at": torch.zeros(4)}, r"at must have shape \(\.\.\., 3\), got \(4,\)"),
        ({"up": torch.zeros(1, 2)}, r"up must have shape \(\.\.\., 3\), got \(1, 2\)"),
    ],
    ids=["at-the-target", "one-at-the-target", "at-shape", "up-shape"],
)
def test_look_at_refuses_a_camera_without_a_direction_and_odd_shapes(kwargs, message):
    with pytest.raises(ValueError, match=message):
        look_at_view_transform(**{"dist": 2.0, **kwargs})


def test_reference_pose_parametrisation_matches_look_at():
    # UNICORN's R = Az @ El @ Ro with T = (0, 0, d) is a look-at camera with azimuth shifted by 180 degrees
    azim, elev = torch.tensor([0.0, 60.0, 250.0]), torch.tensor([30.0, -10.0, 5.0])
    R = azim_elev_roll_to_rotation(azim, elev)
    R_look, _ = look_at_view_transform(2.732, elev, azim + 180.0)
    assert torch.allclose(R, R_look, atol=1e-5)
    roll = azim_elev_roll_to_rotation(torch.zeros(1), torch.zeros(1), torch.tensor([90.0]))
    assert torch.allclose(torch.tensor([[1.0, 0.0, 0.0]]) @ roll[0], torch.tensor([[0.0, 1.0, 0.0]]), atol=1e-6)


def test_euler_angles_compose_axis_rotations():
    angles = torch.tensor([[0.3, -0.2, 1.1]], dtype=torch.float64)
    R = euler_angles_to_matrix(angles, "XYZ")
    c, s = torch.cos(angles[0]), torch.sin(angles[0])
    rx = torch.tensor([[1, 0, 0], [0, c[0], -s[0]], [0, s[0], c[0]]], dtype=torch.float64)
    ry = torch.tensor([[c[1], 0, s[1]], [0, 1, 0], [-s[1], 0, c[1]]], dtype=torch.float64)
    rz = torch.tensor([[c[2], -s[2], 0], [s[2], c[2], 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(R[0], rx @ ry @ rz)
    with pytest.raises(ValueError, match="convention"):
        euler_angles_to_matrix(angles, "XYW")


@pytest.mark.parametrize("at", [0.0, 0.4])
def test_euler_angles_have_the_finite_difference_gradients_at_zero_too(at):
    """Refinement starts from zero angles: the gradient there is finite and matches finite differences."""
    angles = torch.full((2, 3), at, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: euler_angles_to_matrix(a, "ZYX"), (angles,))


def test_rotation_angle_between_is_clamped():
    R = euler_angles_to_matrix(torch.randn(100, 3), "XYZ")
    angle = rotation_angle_between(R, R)
    assert torch.isfinite(angle).all() and angle.max() < 0.1
    Rz = euler_angles_to_matrix(torch.tensor([[0.0, 0.0, math.radians(70)]]), "XYZ")
    assert rotation_angle_between(torch.eye(3)[None], Rz).item() == pytest.approx(70.0, abs=1e-3)


def test_world_to_view_shape_errors():
    with pytest.raises(ValueError, match=r"R must have shape \(2, 3, 3\)"):
        world_to_view(torch.zeros(2, 5, 3), torch.eye(3)[None], torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"verts must have shape"):
        world_to_view(torch.zeros(5, 3), torch.eye(3)[None], torch.zeros(1, 3))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"focal_length": float("nan")}, "focal_length must be a finite number > 0"),
        ({"focal_length": float("inf")}, "focal_length must be a finite number > 0"),
        ({"focal_length": torch.tensor([1.0, 2.0])}, "focal_length must be one number"),
        ({"fov": 30.0, "zfar": float("inf")}, "need 0 <= znear < zfar, both finite"),
        ({"fov": float("nan")}, "fov must be in"),
        ({"fov": "wide"}, "fov must be one number, got 'wide'"),
        ({"fov": [30.0]}, r"fov must be one number, got \[30.0\]"),
        ({"fov": 30.0, "znear": None}, "znear must be one number, got None"),
        ({"fov": 30.0, "zfar": "far"}, "zfar must be one number, got 'far'"),
        # float() reads these as numbers; a flag or a string where an angle belongs is a mistake
        ({"fov": True}, "^fov must be one number, got True$"),
        ({"focal_length": True}, "^focal_length must be one number, got True$"),
        ({"fov": 30.0, "znear": False}, "^znear must be one number, got False$"),
        ({"fov": torch.tensor(True)}, r"^fov must be one number, got tensor\(True\)$"),
        ({"fov": "30"}, "^fov must be one number, got '30'$"),
        # a meta tensor has a shape and no value
        ({"fov": torch.tensor([30.0], device="meta")}, "^fov must be one number, got a tensor on the meta device"),
        ({"fov": 30.0, "zfar": torch.tensor(9.0, device="meta")}, "^zfar must be one number, got a tensor on the meta"),
    ],
)
def test_a_camera_that_cannot_project_is_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PerspectiveCamera(**kwargs)


@pytest.mark.parametrize("frame", [(0.0, 0.0, 64.0, 64.0), (-10.0, -35.0, 120.0, 120.0), (412.5, 80.0, 300.0, 300.0)])
def test_the_opencv_camera_projects_where_the_camera_does(frame):
    """OpenCV's ``K @ (R_cv @ x + t_cv)`` lands where the camera projects a point: in the frame's pixels by NDC
    (+X left, +Y up, pixel (i, j) spanning [j, j + 1) x [i, i + 1)); for the frame (0, 0, S, S), on the pixel centres
    of an S x S render (``ndc_to_pixel``)."""
    torch.manual_seed(0)
    R, T = (t.double() for t in look_at_view_transform(2.7, 20.0, 130.0))
    R = R[0] @ azim_elev_roll_to_rotation(torch.tensor([0.0]), torch.tensor([0.0]), torch.tensor([12.0])).double()[0]
    T = T[0] + torch.tensor([0.1, -0.05, 0.2], dtype=torch.float64)
    points = torch.rand(50, 3, dtype=torch.float64) - 0.5
    camera = PerspectiveCamera(fov=30.0)
    ndc = camera.transform_points(points[None], R[None], T[None])[0]
    K, R_cv, t_cv = opencv_camera(R, T, camera.focal_length, frame)
    assert torch.allclose(R_cv @ R_cv.T, torch.eye(3, dtype=torch.float64), atol=1e-6) and torch.det(R_cv) > 0
    cam = points @ R_cv.T + t_cv
    assert (cam[:, 2] > 0).all()  # in front of the camera: +Z forward
    uv = (cam @ K.T)[:, :2] / cam[:, 2:]
    x, y, width, height = frame
    documented = torch.stack([x + (1 - ndc[:, 0]) / 2 * width, y + (1 - ndc[:, 1]) / 2 * height], dim=-1)
    torch.testing.assert_close(uv, documented - 0.5)  # OpenCV's pixel centres at integers
    if frame[:2] == (0.0, 0.0):
        torch.testing.assert_close(uv, ndc_to_pixel(ndc[:, :2], int(width)))


@pytest.mark.parametrize("convert", [ndc_to_pixel, pixel_to_ndc], ids=lambda f: f.__name__)
@pytest.mark.parametrize("shape", [(5, 1), (5, 3), ()], ids=str)
def test_pixel_conversions_name_points_that_are_not_2d(convert, shape):
    # (5, 1) indexed past its last dimension; (5, 3) dropped its third coordinate without a word
    name = "xy" if convert is ndc_to_pixel else "colrow"
    with pytest.raises(ValueError, match=rf"^{name} must have shape \(\.\.\., 2\), got "):
        convert(torch.zeros(shape), 8)


@pytest.mark.parametrize(
    "focal_length, frame, match",
    [
        (0.0, (0.0, 0.0, 64.0, 64.0), "focal_length must be a finite number > 0, got 0.0"),
        (-2.0, (0.0, 0.0, 64.0, 64.0), "focal_length must be a finite number > 0, got -2.0"),
        (math.nan, (0.0, 0.0, 64.0, 64.0), "focal_length must be a finite number > 0, got nan"),
        (True, (0.0, 0.0, 64.0, 64.0), "focal_length must be one number, got True"),
        ("2", (0.0, 0.0, 64.0, 64.0), "focal_length must be one number, got '2'"),
        (2.0, (0.0, 0.0, 0.0, 64.0), r"frame must be four finite numbers \(x, y, width > 0, height > 0\), got"),
        (2.0, (0.0, 0.0, 64.0, -64.0), "frame must be four finite numbers"),
        (2.0, (0.0, math.inf, 64.0, 64.0), "frame must be four finite numbers"),
        (2.0, (0.0, 0.0, 64.0), "frame must be four finite numbers"),
        (2.0, 64.0, "frame must be four finite numbers"),
        (2.0, "0 0 64 64", "frame must be four finite numbers"),
        (2.0, (0.0, 0.0, "64", 64.0), "frame must be four finite numbers"),
    ],
)
def test_the_opencv_camera_refuses_a_focal_length_or_frame_that_projects_nowhere(focal_length, frame, match):
    # a zero focal length or width flattens K, a negative one mirrors the image, NaN fills it with NaN
    with pytest.raises(ValueError, match=f"^{match}"):
        opencv_camera(torch.eye(3), torch.zeros(3), focal_length, frame)


def test_the_opencv_camera_takes_one_element_tensors_and_numpy_scalars():
    K = opencv_camera(torch.eye(3), torch.zeros(3), 2.0, (0.0, 0.0, 64.0, 64.0))[0]
    got = opencv_camera(torch.eye(3), torch.zeros(3), torch.tensor([2.0]), np.array([0, 0, 64, 64]))[0]
    assert torch.equal(got, K)


def test_world_to_view_refuses_integer_points_rather_than_rounding_the_camera():
    # R and T were cast to the points' dtype: an integer one rounded the rotation to 0 and +-1
    R, T = look_at_view_transform(2.0, 30.0, 45.0)
    points = torch.tensor([[[1, 0, 0]]])
    with pytest.raises(TypeError, match=r"^verts must be a floating point tensor, got torch.int64$"):
        world_to_view(points, R, T)
    with pytest.raises(TypeError, match=r"^verts must be a floating point tensor"):
        PerspectiveCamera(fov=30.0).transform_points_screen(points, R, T, 64)
    torch.testing.assert_close(world_to_view(points.float(), R, T)[0, 0], R[0, 0] + T[0])  # the oracle: row 0 of R
