"""Input validation shared by the metrics (private)."""

from __future__ import annotations

import torch


def check_points(x: torch.Tensor, name: str, dim: int | None = 3) -> torch.Tensor:
    """Check a batched cloud ``(B, N, D)``: floating point, non-empty, finite shape; returns it unchanged."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 3:
        raise ValueError(f"{name} must have shape (B, N, {dim or 'D'}), got {tuple(x.shape)}")
    if dim is not None and x.shape[-1] != dim:
        raise ValueError(f"{name} must have shape (B, N, {dim}), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {x.dtype}")
    if x.shape[0] == 0:
        raise ValueError(f"{name} has an empty batch dimension")
    if x.shape[1] == 0:
        raise ValueError(f"{name} is an empty point cloud (N = 0)")
    return x


def check_same_batch(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Batch sizes and devices of two tensors must match."""
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"batch sizes differ: {name_a} has {a.shape[0]}, {name_b} has {b.shape[0]}")
    if a.device != b.device:
        raise ValueError(f"{name_a} is on {a.device} but {name_b} is on {b.device}")


def check_normals(normals: torch.Tensor | None, points: torch.Tensor, name: str) -> None:
    """Normals, when given, must have the shape of their points."""
    if normals is None:
        return
    if not isinstance(normals, torch.Tensor) or normals.shape != points.shape:
        shape = tuple(normals.shape) if isinstance(normals, torch.Tensor) else type(normals).__name__
        raise ValueError(f"{name} must have the shape of its points {tuple(points.shape)}, got {shape}")
    if not normals.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {normals.dtype}")


def check_rotations(R: torch.Tensor, name: str, batch: int | None = None) -> None:
    """``R`` must be ``(B, 3, 3)`` floating point, with ``B == batch`` when given."""
    if not isinstance(R, torch.Tensor) or R.dim() != 3 or R.shape[1:] != (3, 3):
        shape = tuple(R.shape) if isinstance(R, torch.Tensor) else type(R).__name__
        raise ValueError(f"{name} must have shape (B, 3, 3), got {shape}")
    if not R.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {R.dtype}")
    if batch is not None and R.shape[0] != batch:
        raise ValueError(f"{name} must have batch size {batch}, got {R.shape[0]}")


def check_translations(T: torch.Tensor, name: str, batch: int) -> None:
    """``T`` must be ``(B, 3)`` floating point with ``B == batch``."""
    if not isinstance(T, torch.Tensor) or T.shape != (batch, 3):
        shape = tuple(T.shape) if isinstance(T, torch.Tensor) else type(T).__name__
        raise ValueError(f"{name} must have shape ({batch}, 3), got {shape}")
    if not T.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {T.dtype}")


def check_mesh(verts: torch.Tensor, faces: torch.Tensor) -> None:
    """Batched vertices ``(B, V, 3)`` float and shared faces ``(F, 3)`` long indexing them."""
    check_points(verts, "verts")
    if not isinstance(faces, torch.Tensor) or faces.dim() != 2 or faces.shape[1] != 3:
        shape = tuple(faces.shape) if isinstance(faces, torch.Tensor) else type(faces).__name__
        raise ValueError(f"faces must have shape (F, 3), got {shape}")
    if faces.dtype not in (torch.int32, torch.int64):
        raise TypeError(f"faces must be an integer tensor, got {faces.dtype}")
    if faces.shape[0] == 0:
        raise ValueError("faces is empty (F = 0)")
    if faces.device != verts.device:
        raise ValueError(f"verts is on {verts.device} but faces is on {faces.device}")
    if int(faces.min()) < 0 or int(faces.max()) >= verts.shape[1]:
        raise ValueError(f"faces index vertices outside [0, {verts.shape[1]})")
