"""Perspective camera in unicorn's (PyTorch3D-compatible) NDC and pixel conventions.

- World to view: ``x_view = x_world @ R + T`` (row vectors), view +X left, +Y up, +Z forward.
- Projection: ``x_ndc = f * x / z``, ``y_ndc = f * y / z`` with ``f = 1 / tan(fov / 2)``; depth stays the view z.
- Pixels: for an image of H rows and W columns and ``S = min(H, W)``, the centre of pixel (row i, column j) is at
  ``x_ndc = (W - 1 - 2 j) / S``, ``y_ndc = (H - 1 - 2 i) / S``; for square images this is PyTorch3D's
  ``(1 - (2j + 1) / W, 1 - (2i + 1) / H)``. NDC +X is image-left and +Y image-up.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from unicorn.checks import check_image_size, check_shape, is_real

__all__ = ["PerspectiveCamera", "image_hw", "ndc_to_pixel", "opencv_camera", "pixel_to_ndc", "world_to_view"]


def image_hw(image_size: int | tuple[int, int]) -> tuple[int, int]:
    """(H, W) from an int or a pair of ints, with one error naming ``image_size`` for anything else
    (:func:`unicorn.checks.check_image_size`)."""
    return check_image_size(image_size)


def world_to_view(verts: torch.Tensor, R: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """``verts @ R + T``: (B, V, 3) world points to view coordinates, with R (B, 3, 3) and T (B, 3), in verts' dtype.

    Raises:
        unicorn.checks.ShapeError: shapes outside these.
        TypeError: ``verts`` not floating point (R and T cast to an integer dtype would be rounded).
    """
    dims = check_shape(verts, "B, V, 3", "verts", floating=True)
    check_shape(R, "B, 3, 3", "R", dims)
    check_shape(T, "B, 3", "T", dims)
    return verts @ R.to(verts) + T.to(verts).unsqueeze(1)


def ndc_to_pixel(xy: torch.Tensor, image_size: int | tuple[int, int]) -> torch.Tensor:
    """NDC (..., 2) to continuous pixel coordinates (column, row), pixel centres at integers.

    Raises:
        unicorn.checks.ShapeError: ``xy`` not of shape (..., 2).
    """
    check_shape(xy, "*, 2", "xy")
    H, W = image_hw(image_size)
    S = min(H, W)
    col = (W - 1 - xy[..., 0] * S) / 2
    row = (H - 1 - xy[..., 1] * S) / 2
    return torch.stack([col, row], dim=-1)


def pixel_to_ndc(colrow: torch.Tensor, image_size: int | tuple[int, int]) -> torch.Tensor:
    """Continuous pixel coordinates (column, row) (..., 2) to NDC, the inverse of :func:`ndc_to_pixel`.

    Raises:
        unicorn.checks.ShapeError: ``colrow`` not of shape (..., 2).
    """
    check_shape(colrow, "*, 2", "colrow")
    H, W = image_hw(image_size)
    S = min(H, W)
    x = (W - 1 - 2 * colrow[..., 0]) / S
    y = (H - 1 - 2 * colrow[..., 1]) / S
    return torch.stack([x, y], dim=-1)


def opencv_camera(
    R: torch.Tensor, T: torch.Tensor, focal_length: float, frame: tuple[float, float, float, float]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The camera ``x_view = x @ R + T`` with ``focal_length`` (NDC) in OpenCV's convention, for other tools.

    OpenCV's camera (``cv2.projectPoints``, COLMAP): ``x_cam = R_cv @ x + t_cv`` with +X right, +Y down, +Z forward,
    and pixel ``(u, v, 1) ~ K @ x_cam``, pixel centres at integers. The pixels are those of an image in which the
    NDC square ``[-1, 1]`` spans ``frame = (x, y, width, height)`` (in pixels whose pixel (i, j) spans
    ``[j, j + 1) x [i, i + 1)``, as ``unicorn-reconstruct``'s ``pose.json`` records it for the photo); the frame
    ``(0, 0, S, S)`` gives the pixels of the S x S rendered image (:func:`ndc_to_pixel`).

    Args:
        R: (3, 3) rotation, T: (3,) translation (row-vector convention above).
        focal_length: the camera's focal length in NDC units.
        frame: ``(x, y, width, height)``.

    Returns:
        K (3, 3), R_cv (3, 3) and t_cv (3,), in R's dtype.

    Raises:
        unicorn.checks.ShapeError: ``R`` or ``T`` of another shape.
        ValueError: ``focal_length`` not a finite number > 0, or ``frame`` not four finite numbers with width and
            height > 0 (K would hold NaN, or mirror or flatten the image).
    """
    check_shape(R, "3, 3", "R")
    check_shape(T, "3", "T")
    focal_length = _one_number("focal_length", focal_length)
    if not (math.isfinite(focal_length) and focal_length > 0):
        raise ValueError(f"focal_length must be a finite number > 0, got {focal_length}")
    try:
        values = [_one_number("frame", v) for v in frame] if not isinstance(frame, str) else []
    except (TypeError, ValueError):  # not iterable, or an entry that is no number
        values = []
    if not (len(values) == 4 and all(map(math.isfinite, values)) and values[2] > 0 and values[3] > 0):
        raise ValueError(f"frame must be four finite numbers (x, y, width > 0, height > 0), got {frame!r}")
    x, y, width, height = values
    flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=R.dtype, device=R.device))  # view +X left, +Y up
    K = torch.tensor(
        [
            [focal_length * width / 2, 0.0, x + width / 2 - 0.5],
            [0.0, focal_length * height / 2, y + height / 2 - 0.5],
            [0.0, 0.0, 1.0],
        ],
        dtype=R.dtype,
        device=R.device,
    )
    return K, flip @ R.T, flip @ T.to(R)


def _one_number(name: str, value: object) -> float:
    """``value`` as a float (a one-element tensor or NumPy scalar included), or a ValueError naming ``name``. A
    bool or a string is no number, though ``float`` reads ``True`` as 1 and ``"30"`` as 30; a meta tensor has no
    value to read."""
    real = is_real(value)
    scalar = torch.is_tensor(value) and value.numel() == 1 and not (value.dtype == torch.bool or value.is_complex())
    if not (real or scalar):
        raise ValueError(f"{name} must be one number, got {value!r}")
    if scalar and value.is_meta:  # type: ignore[union-attr]
        raise ValueError(f"{name} must be one number, got a tensor on the meta device, which holds no value")
    return float(value)  # type: ignore[arg-type]


class PerspectiveCamera(nn.Module):
    """Pinhole camera with a square-pixel perspective projection.

    Give either ``fov`` (degrees, full angle spanning NDC [-1, 1]) or ``focal_length`` (in NDC units), not both.
    ``znear`` and ``zfar`` are used only by aggregators that normalise depth (SoftRas); the rasterizer never
    clips against them.

    The focal length is kept as a Python float, so that a float64 projection is exact to float64 whatever the
    module's dtype.

    Example:
        >>> cam = PerspectiveCamera(fov=30.0)
        >>> round(cam.focal_length, 4)
        3.7321
    """

    focal_length: float

    def __init__(
        self,
        fov: float | None = None,
        focal_length: float | None = None,
        znear: float = 1.0,
        zfar: float = 100.0,
    ) -> None:
        super().__init__()
        if (fov is None) == (focal_length is None):
            raise ValueError("give exactly one of fov (degrees) or focal_length (NDC units)")
        if fov is not None:
            fov = _one_number("fov", fov)
            if not 0.0 < fov < 180.0:
                raise ValueError(f"fov must be in (0, 180) degrees, got {fov}")
            focal_length = 1.0 / math.tan(math.radians(fov) / 2.0)
        focal_length = _one_number("focal_length", focal_length)
        if not (math.isfinite(focal_length) and focal_length > 0):
            raise ValueError(f"focal_length must be a finite number > 0, got {focal_length}")
        znear, zfar = _one_number("znear", znear), _one_number("zfar", zfar)
        if not (0.0 <= znear < zfar and math.isfinite(zfar)):
            raise ValueError(f"need 0 <= znear < zfar, both finite, got znear={znear}, zfar={zfar}")
        self.focal_length = float(focal_length)
        self.znear = float(znear)
        self.zfar = float(zfar)

    @property
    def fov(self) -> float:
        """Full field of view in degrees."""
        return math.degrees(2.0 * math.atan(1.0 / self.focal_length))

    def extra_repr(self) -> str:
        return f"focal_length={self.focal_length:.4f}, znear={self.znear}, zfar={self.zfar}"

    def project(self, verts_view: torch.Tensor) -> torch.Tensor:
        """View points (..., 3) to ``(x_ndc, y_ndc, z_view)`` (..., 3).

        Points with z <= 0 (behind the camera) get finite but meaningless x, y; the rasterizer skips their faces.
        """
        z = verts_view[..., 2]
        safe_z = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
        xy = self.focal_length * verts_view[..., :2] / safe_z.unsqueeze(-1)
        return torch.cat([xy, z.unsqueeze(-1)], dim=-1)

    def transform_points(self, verts: torch.Tensor, R: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
        """World points (B, V, 3) to ``(x_ndc, y_ndc, z_view)`` (B, V, 3)."""
        return self.project(world_to_view(verts, R, T))

    def transform_points_screen(
        self, verts: torch.Tensor, R: torch.Tensor, T: torch.Tensor, image_size: int | tuple[int, int]
    ) -> torch.Tensor:
        """World points (B, V, 3) to ``(column, row, z_view)`` in pixels, pixel centres at integers."""
        ndc = self.transform_points(verts, R, T)
        return torch.cat([ndc_to_pixel(ndc[..., :2], image_size), ndc[..., 2:]], dim=-1)
