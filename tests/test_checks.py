"""unicorn.checks: the one input-checks module of render, metrics and evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from unicorn.checks import (
    FaceIndexError,
    check_faces,
    check_image_size,
    check_mesh,
    check_rotations,
    check_same_dtype,
)

FACES = torch.tensor([[0, 1, 2], [0, 2, 3]])


def test_face_indices_outside_the_vertices() -> None:
    for call in (lambda: check_faces(FACES, 3), lambda: check_mesh(torch.zeros(1, 3, 3), FACES)):
        with pytest.raises(FaceIndexError, match=r"face indices must be in \[0, 3\), got range \[0, 3\]"):
            call()
    # both kinds of callers catch it: the renderer's (IndexError) and the metrics' (ValueError)
    assert issubclass(FaceIndexError, IndexError) and issubclass(FaceIndexError, ValueError)
    with pytest.raises(FaceIndexError, match=r"got range \[-1, 2\]"):
        check_faces(torch.tensor([[-1, 1, 2]]), 4)


@pytest.mark.parametrize("dtype", [torch.int16, torch.int32, torch.int64, torch.uint8])
def test_any_integer_faces(dtype: torch.dtype) -> None:
    check_mesh(torch.zeros(2, 4, 3), FACES.to(dtype))


def test_layout_and_type_errors() -> None:
    verts = torch.zeros(2, 4, 3)
    with pytest.raises(TypeError, match="faces must be an integer tensor"):
        check_mesh(verts, FACES.float())
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\), got \(2, 2\)"):
        check_mesh(verts, FACES[:, :2])
    with pytest.raises(ValueError, match=r"verts must have shape \(B, N, 3\)"):
        check_mesh(verts[0], FACES)
    with pytest.raises(TypeError, match="float32 or float64"):
        check_mesh(verts.half(), FACES)


def test_empty_meshes_only_where_allowed() -> None:
    empty = torch.zeros(0, 3, dtype=torch.long)
    check_mesh(torch.zeros(0, 4, 3), empty, allow_empty=True)
    check_mesh(torch.zeros(1, 0, 3), empty, allow_empty=True, finite=True)
    with pytest.raises(ValueError, match="faces is empty"):
        check_mesh(torch.zeros(1, 4, 3), empty)
    with pytest.raises(ValueError, match="empty batch"):
        check_mesh(torch.zeros(0, 4, 3), FACES)


def test_finite_vertices_when_asked() -> None:
    verts = torch.zeros(1, 4, 3)
    verts[0, 2, 1] = float("nan")
    check_mesh(verts, FACES)  # not asked
    with pytest.raises(ValueError, match="NaN or infinite"):
        check_mesh(verts, FACES, finite=True)
    with pytest.raises(ValueError, match="NaN or infinite"):
        check_mesh(verts, torch.zeros(0, 3, dtype=torch.long), allow_empty=True, finite=True)


@pytest.mark.parametrize("size", [2.5, "abc", True, None, (4, 4.0), ("4", 4), (True, 4)])
def test_image_size_of_another_type_is_named(size) -> None:
    with pytest.raises(TypeError, match=r"^image_size must be a positive int or \(H, W\) of ints, got "):
        check_image_size(size)


@pytest.mark.parametrize("size", [0, -1, (4,), (4, 4, 4), (0, 4)])
def test_image_size_of_another_value_is_named(size) -> None:
    with pytest.raises(ValueError, match=r"^side must be a positive int or \(H, W\), got "):
        check_image_size(size, "side")


def test_image_sizes() -> None:
    assert check_image_size(5) == (5, 5)
    assert check_image_size([3, 4]) == (3, 4) and check_image_size(torch.Size([3, 4])) == (3, 4)
    assert check_image_size((np.int64(3), 4)) == (3, 4)


def test_same_dtype() -> None:
    check_same_dtype(torch.zeros(2), torch.zeros(3), "a", "b")
    with pytest.raises(TypeError, match=r"^verts is torch.float64 but colors is torch.float32: give both the same"):
        check_same_dtype(torch.zeros(2, dtype=torch.float64), torch.zeros(2), "verts", "colors")


def test_finite_also_is_read_with_the_mesh() -> None:
    verts, colors = torch.zeros(1, 4, 3), torch.zeros(1, 4, 3)
    check_mesh(verts, FACES, finite=True, finite_also={"colors": colors})
    colors[0, 1, 1] = float("inf")
    with pytest.raises(ValueError, match="^colors contains NaN or infinite values$"):
        check_mesh(verts, FACES, finite_also={"colors": colors})
    verts[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="^verts contains NaN"):  # the vertices first
        check_mesh(verts, FACES, finite=True, finite_also={"colors": colors})


def test_rotations_name_the_expected_batch() -> None:
    with pytest.raises(ValueError, match=r"R must have shape \(2, 3, 3\), got \(1, 3, 3\)"):
        check_rotations(torch.zeros(1, 3, 3), "R", 2)
    with pytest.raises(TypeError, match="R must be a floating point tensor, got torch.int64"):
        check_rotations(torch.zeros(2, 3, 3, dtype=torch.long), "R", 2)
