import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.metrics.pose import (
    align_canonical_frame,
    azimuth_error,
    geodesic_error,
    pose_errors,
    rotation_to_azim_elev_roll,
)


def random_rotations(n, seed):
    return axis_angle_to_rotation_matrix(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)) * 2)


def test_geodesic_error_known_angles():
    axis = torch.nn.functional.normalize(torch.tensor([1.0, 2.0, -0.5]), dim=0)
    angles = torch.tensor([0.0, 1e-3, 1.0, 30.0, 90.0, 179.0, 180.0], dtype=torch.float64)
    R = axis_angle_to_rotation_matrix(axis.double() * torch.deg2rad(angles).unsqueeze(1))
    base = random_rotations(1, 0).double()
    err = geodesic_error(base, base @ R)
    torch.testing.assert_close(err, angles, atol=1e-4, rtol=0)
    assert geodesic_error(base.float(), base.float()).item() == pytest.approx(0.0, abs=1e-3)


def test_azimuth_error_and_extraction():
    torch.testing.assert_close(
        azimuth_error(torch.tensor([350.0, 10.0, -170.0]), torch.tensor([10.0, 200.0, 170.0])),
        torch.tensor([20.0, 170.0, 20.0]),
    )
    azim, elev, roll = (
        torch.tensor([10.0, -170.0, 95.0]),
        torch.tensor([20.0, -45.0, 80.0]),
        torch.tensor([5.0, -30.0, 170.0]),
    )
    out = rotation_to_azim_elev_roll(azim_elev_roll_to_rotation(azim, elev, roll))
    for got, want in zip(out, (azim, elev, roll)):
        torch.testing.assert_close(got, want, atol=1e-3, rtol=0)


def test_elevations_near_the_poles_are_read_back_in_float32() -> None:
    """Within 1e-3 degrees of the angles a float32 rotation was made from, up to 0.01 degree from the pole."""
    elev = torch.tensor([89.99, 89.9, -89.95, 89.5, -60.0])
    azim, roll = torch.full_like(elev, 30.0), torch.full_like(elev, 10.0)
    out = rotation_to_azim_elev_roll(azim_elev_roll_to_rotation(azim, elev, roll))
    for got, want in zip(out, (azim, elev, roll)):
        torch.testing.assert_close(got, want, atol=1e-3, rtol=0)


def test_align_canonical_frame_with_outliers():
    R_gt = random_rotations(300, 1)
    Q = random_rotations(1, 2)[0]
    noise = axis_angle_to_rotation_matrix(torch.randn(300, 3, generator=torch.Generator().manual_seed(3)) * 0.03)
    R_pred = Q.T @ R_gt @ noise  # so that R_gt ~ Q @ R_pred
    flip = azim_elev_roll_to_rotation(torch.tensor(180.0), torch.tensor(0.0))
    R_pred[:90] = flip @ R_pred[:90]  # 30% of images with a flipped canonical frame
    Q_est = align_canonical_frame(R_pred, R_gt)
    assert geodesic_error(Q_est, Q).item() < 1.0
    errors = pose_errors(R_pred, R_gt, align=True)
    assert errors["rot-err-median"] < 5.0
    assert errors["rot-acc-30"] == pytest.approx(0.7, abs=0.01)
    assert errors["rot-flip-150"] == pytest.approx(0.3, abs=0.01)  # the flipped frames, and only them
    assert set(errors) == {
        "rot-err-mean",
        "rot-err-median",
        "rot-acc-30",
        "rot-flip-150",
        "azim-err-mean",
        "azim-err-median",
    }
    assert set(pose_errors(R_pred, R_gt, accuracy_threshold=15.0, flip_threshold=170.5)) >= {
        "rot-acc-15",
        "rot-flip-170.5",
    }
    unaligned = pose_errors(R_pred, R_gt)
    assert unaligned["rot-err-median"] > 10.0


def test_pose_errors_exact():
    R_gt = azim_elev_roll_to_rotation(torch.tensor([0.0, 90.0]), torch.tensor([30.0, 30.0]))
    R_pred = azim_elev_roll_to_rotation(torch.tensor([10.0, 90.0]), torch.tensor([30.0, 30.0]))
    errors = pose_errors(R_pred, R_gt)
    assert errors["azim-err-mean"] == pytest.approx(5.0, abs=1e-3)
    assert errors["rot-acc-30"] == 1.0
    with pytest.raises(ValueError, match="shape"):
        pose_errors(R_pred[:, :2], R_gt)


def test_geodesic_error_equals_scipy():
    from scipy.spatial.transform import Rotation

    R1, R2 = random_rotations(64, 1).double(), random_rotations(64, 2).double()
    expected = Rotation.from_matrix((R1.transpose(1, 2) @ R2).numpy()).magnitude() * 180 / torch.pi
    torch.testing.assert_close(geodesic_error(R1, R2), torch.from_numpy(expected), atol=1e-4, rtol=0)


def test_the_medians_of_an_even_number_of_views_are_the_mean_of_the_middle_two() -> None:
    off = torch.tensor([0.0, 10.0, 40.0, 70.0])  # azimuth errors, degrees, about the vertical axis
    R_gt = azim_elev_roll_to_rotation(torch.zeros(4), torch.zeros(4), torch.zeros(4))
    R_pred = azim_elev_roll_to_rotation(off, torch.zeros(4), torch.zeros(4))
    errors = pose_errors(R_pred, R_gt, align=False)
    expected = 25.0  # (10 + 40) / 2; torch.median gives 10
    assert errors["rot-err-median"] == pytest.approx(expected, abs=1e-3)
    assert errors["azim-err-median"] == pytest.approx(expected, abs=1e-3)


def test_errors_aligned_on_one_view_are_refused() -> None:
    """The rotation aligning one view makes its error 0 whatever the prediction."""
    R_gt = azim_elev_roll_to_rotation(torch.zeros(1), torch.zeros(1), torch.zeros(1))
    R_pred = azim_elev_roll_to_rotation(torch.tensor([120.0]), torch.zeros(1), torch.zeros(1))
    assert pose_errors(R_pred, R_gt)["rot-err-mean"] == pytest.approx(120.0, abs=1e-3)
    with pytest.raises(ValueError, match="^aligning the canonical frame needs at least 2 rotations, got 1$"):
        pose_errors(R_pred, R_gt, align=True)
