"""Rotations and camera placements in unicorn's (PyTorch3D-compatible) convention.

Points are row vectors and the world-to-view transform is ``x_view = x_world @ R + T``. The view frame has
+X pointing to the image left, +Y up and +Z forward (away from the camera), as in PyTorch3D, so the released
UNICORN checkpoints and the ShapeNet pose conversion apply unchanged.

Angles are in degrees unless a function says otherwise. Two azimuths meet here: :func:`look_at_view_transform`'s
(PyTorch3D's) puts the camera on +Z at azimuth 0 and on +X at 90; UNICORN's pose angles
(:func:`azim_elev_roll_to_rotation`, which the model predicts and the synthetic datasets record) put it half a turn
round, on -Z at 0 and on -X at 90. Positive elevation is above the object (+Y) in both.

Python numbers given with tensors take the tensors' dtype and device (a float64 batch stays float64, a CUDA one on
CUDA), as in torch's arithmetic.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch

from unicorn.checks import NonFiniteValueError, check_shape

__all__ = [
    "azim_elev_roll_to_rotation",
    "camera_position_from_spherical",
    "euler_angles_to_matrix",
    "look_at_rotation",
    "look_at_view_parameters",
    "look_at_view_transform",
    "rotation_angle_between",
]

_AXES = {"X": 0, "Y": 1, "Z": 2}


def _matrix(rows: list[list[torch.Tensor]]) -> torch.Tensor:
    """(..., 3, 3) matrices from three rows of three (...,) entries."""
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def _as_tensors(*values: torch.Tensor | float) -> list[torch.Tensor]:
    """``values`` as tensors of one floating dtype, the Python numbers on the first tensor's device: the tensors'
    promoted dtype, as torch's arithmetic gives it (the default dtype for integer tensors or none). A number made a
    float32 tensor by itself would round a float64 camera's angles, and sit on the CPU beside a CUDA batch."""
    tensors = [v for v in values if isinstance(v, torch.Tensor)]
    dtype = functools.reduce(torch.promote_types, [t.dtype for t in tensors]) if tensors else None
    if dtype is None or not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    device = tensors[0].device if tensors else None
    return [torch.as_tensor(v, dtype=dtype, device=device) for v in values]


def azim_elev_roll_to_rotation(
    azim: torch.Tensor, elev: torch.Tensor, roll: torch.Tensor | None = None
) -> torch.Tensor:
    """Rotation of a camera looking at the origin, as UNICORN parametrises poses.

    ``R = Az(azim) @ El(elev) @ Ro(roll)`` with row-vector matrices: azimuth about +Y, elevation about +X with
    positive elevation putting the camera above the object, roll about the optical axis. With ``T = (0, 0, dist)``
    and no roll, this is the camera ``look_at_view_transform(dist, elev, azim + 180)``: azimuth 0 puts the camera on
    -Z (R is the identity), 90 on -X.

    Args:
        azim: (...,) azimuth in degrees.
        elev: (...,) elevation in degrees.
        roll: (...,) roll in degrees, zero when omitted.

    Returns:
        (..., 3, 3) rotation matrices, to be used as ``x @ R``.
    """
    if roll is None:
        azim, elev = _as_tensors(azim, elev)
        roll = torch.zeros_like(azim)  # made on the device: a number would be copied there
    else:
        azim, elev, roll = _as_tensors(azim, elev, roll)
    azim, elev, roll = torch.broadcast_tensors(azim, elev, roll)
    a, e, r = torch.deg2rad(azim), torch.deg2rad(-elev), torch.deg2rad(roll)
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    ca, sa, ce, se, cr, sr = a.cos(), a.sin(), e.cos(), e.sin(), r.cos(), r.sin()
    r_azim = _matrix([[ca, zero, sa], [zero, one, zero], [-sa, zero, ca]])
    r_elev = _matrix([[one, zero, zero], [zero, ce, se], [zero, -se, ce]])
    r_roll = _matrix([[cr, sr, zero], [-sr, cr, zero], [zero, zero, one]])
    return r_azim @ r_elev @ r_roll


def _axis_rotation(axis: str, angle: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) column-vector rotations by ``angle`` (N,) radians about ``axis``: cosines and sines only, so exact
    to rounding and with finite gradients at 0 (a general axis-angle map divides by the angle)."""
    c, s = angle.cos(), angle.sin()
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    rows = {
        "X": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
        "Y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
        "Z": [[c, -s, zero], [s, c, zero], [zero, zero, one]],
    }[axis]
    return _matrix(rows)


def euler_angles_to_matrix(angles: torch.Tensor, convention: str = "XYZ") -> torch.Tensor:
    """Rotation matrices from Euler angles (radians), composed as ``R_a @ R_b @ R_c`` for convention ``"abc"``.

    Each factor is the column-vector rotation about one axis, the PyTorch3D convention; pass the result as ``R`` to
    rotate the world by its transpose.

    Args:
        angles: (..., 3) angles in radians, one per letter of ``convention``.
        convention: three letters from ``"XYZ"``, e.g. ``"XYZ"`` or ``"ZYX"``.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    if len(convention) != 3 or any(c not in _AXES for c in convention):
        raise ValueError(f"convention must be three letters among 'X', 'Y', 'Z', got {convention!r}")
    check_shape(angles, "*, 3", "angles")
    batch = angles.shape[:-1]
    flat = angles.reshape(-1, 3)
    result = None
    for i, axis in enumerate(convention):
        rot = _axis_rotation(axis, flat[:, i])
        result = rot if result is None else result @ rot
    return result.reshape(*batch, 3, 3)


def camera_position_from_spherical(
    dist: torch.Tensor | float, elev: torch.Tensor | float, azim: torch.Tensor | float
) -> torch.Tensor:
    """Camera centre (..., 3) at distance ``dist``, elevation and azimuth (degrees) around the origin.

    Azimuth 0 looks from +Z, azimuth 90 from +X, positive elevation from above (+Y).
    """
    dist, elev, azim = torch.broadcast_tensors(*_as_tensors(dist, elev, azim))
    e, a = torch.deg2rad(elev), torch.deg2rad(azim)
    return torch.stack([dist * e.cos() * a.sin(), dist * e.sin(), dist * e.cos() * a.cos()], dim=-1)


def look_at_rotation(
    camera_position: torch.Tensor, at: torch.Tensor | None = None, up: torch.Tensor | None = None
) -> torch.Tensor:
    """Rotation (row-vector convention) of a camera at ``camera_position`` looking at ``at``; the three tensors
    broadcast together (one ``up`` for many cameras, or many for one camera), as in PyTorch3D.

    Args:
        camera_position: (..., 3) camera centres in world coordinates.
        at: (..., 3) target points, the origin by default.
        up: (..., 3) world up direction, +Y by default. A camera looking along it (to rounding) takes as X axis
            the cross product of the world axis least aligned with its viewing direction and that direction.

    Returns:
        (..., 3, 3) rotations ``R`` whose columns are the camera's X (left), Y (up) and Z (forward) axes in world
        coordinates, so that ``(x - camera_position) @ R`` are view coordinates.

    Raises:
        ValueError: a tensor not of shape (..., 3), tensors that do not broadcast together, a camera at its
            target point (no viewing direction), or an ``up`` of (0, 0, 0) (no direction).
        unicorn.checks.NonFiniteValueError: NaN or infinite values (a ``ValueError``).
    """
    check_shape(camera_position, "*, 3", "camera_position")
    at = torch.zeros_like(camera_position) if at is None else at.to(camera_position)
    if up is None:
        up = camera_position.new_tensor([0.0, 1.0, 0.0]).expand_as(camera_position)
    check_shape(at, "*, 3", "at")
    check_shape(up, "*, 3", "up")
    try:
        camera_position, at, up = torch.broadcast_tensors(camera_position, at, up.to(camera_position))
    except RuntimeError:
        raise ValueError(
            f"look_at: camera_position {tuple(camera_position.shape)}, at {tuple(at.shape)} and up "
            f"{tuple(up.shape)} do not broadcast together"
        ) from None
    forward = at - camera_position
    not_finite, at_target, no_up = torch.stack(  # one device read for the three refusals
        [
            ~(torch.isfinite(camera_position).all() & torch.isfinite(at).all() & torch.isfinite(up).all()),
            (forward.norm(dim=-1) < 1e-8).any(),
            (up == 0).all(dim=-1).any(),
        ]
    ).tolist()
    if not_finite:
        raise NonFiniteValueError("look_at: camera_position, at or up contains NaN or infinite values")
    if at_target:
        raise ValueError("look_at: a camera is at the point it looks at (distance 0), so it has no viewing direction")
    if no_up:
        raise ValueError("look_at: an up vector is (0, 0, 0), which gives no direction")
    z_axis = torch.nn.functional.normalize(forward, dim=-1)
    side = torch.cross(up, z_axis, dim=-1)
    norm = side.norm(dim=-1, keepdim=True)
    # looking along `up` to rounding (a camera straight above its target): any x axis orthogonal to z will do. A
    # fixed floor on the norm instead (normalize's eps) would leave x shorter than 1 in float64, and R no rotation
    eps = torch.finfo(z_axis.dtype).eps
    degenerate = norm <= 4 * eps * up.norm(dim=-1, keepdim=True)
    x_axis = side / torch.where(degenerate, 1.0, norm)  # not by a zero norm: its gradient would be NaN
    if degenerate.any():
        # the world axis least aligned with z, so that the cross product is never 0 (the X axis is when up is X)
        x_ref = torch.nn.functional.one_hot(z_axis.abs().argmin(dim=-1), 3).to(z_axis)
        alt = torch.nn.functional.normalize(torch.cross(x_ref, z_axis, dim=-1), dim=-1)
        x_axis = torch.where(degenerate, alt, x_axis)
    y_axis = torch.nn.functional.normalize(torch.cross(z_axis, x_axis, dim=-1), dim=-1)
    return torch.stack([x_axis, y_axis, z_axis], dim=-1)


def look_at_view_transform(
    dist: torch.Tensor | float = 1.0,
    elev: torch.Tensor | float = 0.0,
    azim: torch.Tensor | float = 0.0,
    at: torch.Tensor | Sequence[Sequence[float]] | None = None,
    up: torch.Tensor | Sequence[Sequence[float]] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-view ``(R, T)`` of cameras placed by distance, elevation and azimuth (degrees): azimuth 0 puts the
    camera on +Z, 90 on +X, positive elevation above (+Y), as :func:`camera_position_from_spherical` places it
    (PyTorch3D's convention; UNICORN's pose angles are half a turn round, see :func:`azim_elev_roll_to_rotation`).

    Args:
        dist, elev, azim: the camera's distance to ``at`` and its elevation and azimuth (degrees), scalars or
            tensors that broadcast together.
        at: (B, 3) or (3,) points looked at (tensors or nested lists, as PyTorch3D's ``at=((0, 0, 0),)``); the
            origin by default.
        up: (B, 3) or (3,) world up directions; +Y by default, and straight above or below the target (elev +-90,
            where +Y is the viewing direction) the limit of the views beside the pole, which turns with ``azim``.

    Returns:
        R: (B, 3, 3) and T: (B, 3) with ``x_view = x_world @ R + T``; B is the broadcast size of the inputs
        (1 for scalars).

    Raises:
        ValueError: ``at`` or ``up`` not of shape (..., 3), batches of cameras, ``at`` and ``up`` of different sizes
            (other than 1), a camera at distance 0 from ``at``, an ``up`` of (0, 0, 0), or NaN or infinite values
            (:func:`look_at_rotation`).
    """
    dist, elev, azim = torch.broadcast_tensors(*_as_tensors(dist, elev, azim))
    eye = camera_position_from_spherical(dist, elev, azim).reshape(-1, 3)
    sizes = {"cameras (dist, elev, azim)": eye.shape[0]}
    if at is not None:
        at = torch.as_tensor(at)  # PyTorch3D's callers pass lists: at=[(0, 0, 0)]
        check_shape(at, "*, 3", "at")
        at = at.reshape(-1, 3).to(eye)
        sizes["at points"] = at.shape[0]
    if up is not None:
        up = torch.as_tensor(up)
        check_shape(up, "*, 3", "up")
        up = up.reshape(-1, 3).to(eye)
        sizes["up directions"] = up.shape[0]
    if any(n not in (1, max(sizes.values())) for n in sizes.values()):
        given = ", ".join(f"{n} {name}" for name, n in sizes.items())
        raise ValueError(f"look_at_view_transform: {given}; each number must be 1 or the same as the others")
    if at is not None:
        eye = eye + at
    if up is None:
        up = _orbit_up(elev, azim).reshape(-1, 3)
    R = look_at_rotation(eye, at, up)
    T = -(eye.unsqueeze(1) @ R).squeeze(1)
    return R, T


def _orbit_up(elev: torch.Tensor, azim: torch.Tensor) -> torch.Tensor:
    """(..., 3) the +Y axis of a camera at ``elev``, ``azim`` (degrees, (...,)) looking at its centre with world up
    +Y: the direction of growing elevation, turned over past the poles (cos(elev) < 0), as +Y makes it. Unlike +Y
    it is defined at the poles (elev = +-90, where cos(elev) is rounding of either sign): there it is the limit from
    the equator's side, so a view from straight above turns with the azimuth as the views just below it do."""
    e, a = torch.deg2rad(elev), torch.deg2rad(azim)
    up = torch.stack([-e.sin() * a.sin(), e.cos(), -e.sin() * a.cos()], dim=-1)
    over = (e.cos() < 0) & (torch.remainder(elev, 180.0) != 90.0)
    return torch.where(over.unsqueeze(-1), -up, up)


def look_at_view_parameters(R: torch.Tensor, T: torch.Tensor) -> dict[str, torch.Tensor]:
    """Inverse of :func:`look_at_view_transform`: the arguments that give back the camera ``(R, T)``.

    ``at`` is the point of the optical axis at the depth of the world origin (``T[..., 2]`` in front of the
    camera), so ``dist`` is that depth; ``up`` is the camera's own +Y axis, which carries the roll. For a camera
    looking at the origin with no roll, ``at`` is 0 and ``up`` may be left out (+Y gives the same camera):
    ``look_at_view_transform(dist, elev, azim)`` alone gives it back. A camera straight above or below its target
    (``elev`` +-90, where azimuth and roll are one turn) takes the azimuth of its ``up``, and so is such a camera.

    Args:
        R: (..., 3, 3) world-to-view rotations (``x_view = x_world @ R + T``).
        T: (..., 3) translations; the world origin must be in front of the camera (``T[..., 2] > 0``).

    Returns:
        ``dist`` (...), ``elev`` (...) and ``azim`` (...) in degrees, ``at`` (..., 3) and ``up`` (..., 3) such
        that ``look_at_view_transform(dist, elev, azim, at, up)`` equals ``(R, T)`` (flattened to one batch).
    """
    dims = check_shape(R, "*N, 3, 3", "R")
    check_shape(T, "*N, 3", "T", dims)
    centre = -(T.unsqueeze(-2) @ R.transpose(-1, -2)).squeeze(-2)  # x_view = 0
    forward, up = R[..., :, 2], R[..., :, 1]  # the camera's +Z and +Y axes in world coordinates
    dist = T[..., 2]
    at = centre + dist.unsqueeze(-1) * forward
    back = -forward  # direction from `at` to the camera
    horizontal = torch.hypot(back[..., 0], back[..., 2])
    # atan2, not asin(back_y): as accurate near the poles as elsewhere (asin puts float32's 89.99 degrees at 90)
    elev = torch.rad2deg(torch.atan2(back[..., 1], horizontal))
    azim = torch.rad2deg(torch.atan2(back[..., 0], back[..., 2]))
    # at a pole the horizontal part of `back` is rounding: the azimuth is read from up, as look_at_view_transform
    # turns it there (the camera's +Y is -sin(elev) (sin(azim), 0, cos(azim)))
    pole = horizontal <= 4 * torch.finfo(back.dtype).eps
    sign = back[..., 1].sign()
    elev = torch.where(pole, 90.0 * sign, elev)
    azim = torch.where(pole, torch.rad2deg(torch.atan2(-sign * up[..., 0], -sign * up[..., 2])), azim)
    return {"dist": dist, "elev": elev, "azim": azim, "at": at, "up": up}


def rotation_angle_between(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in degrees, in [0, 180], between rotations (..., 3, 3).

    Computed as ``atan2(|vee(M - M^T)| / 2, (tr M - 1) / 2)`` with ``M = R1^T R2``: accurate near 0 and 180
    degrees and never NaN, unlike ``acos`` of the trace (which the reference left unclamped).
    """
    check_shape(R1, "*, 3, 3", "R1")
    check_shape(R2, "*, 3, 3", "R2")
    M = R1.transpose(-1, -2) @ R2.to(R1)
    cos = (M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    skew = torch.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    sin = torch.linalg.vector_norm(skew, dim=-1) / 2
    return torch.rad2deg(torch.atan2(sin, cos))
