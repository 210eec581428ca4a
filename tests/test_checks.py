"""unicorn.checks: the one input-checks module of render, metrics and evaluation."""

from __future__ import annotations

import pytest
import torch

from unicorn.checks import FaceIndexError, check_faces, check_mesh

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
