"""unicorn.checks: the one input-checks module of render, metrics and evaluation."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from unicorn.checks import (
    FaceIndexError,
    ShapeError,
    check_faces,
    check_image_size,
    check_mesh,
    check_rotations,
    check_same_dtype,
    check_shape,
)
from unicorn.geometry.mesh import ellipsoid
from unicorn.geometry.rotations import look_at_view_transform
from unicorn.render import TexturesVertex, build_renderer, list_renderers

FACES = torch.tensor([[0, 1, 2], [0, 2, 3]])


def test_face_indices_outside_the_vertices() -> None:
    for call in (lambda: check_faces(FACES, 3), lambda: check_mesh(torch.zeros(1, 3, 3), FACES)):
        with pytest.raises(FaceIndexError, match=r"face indices must be in \[0, 3\), got range \[0, 3\]"):
            call()
    # both kinds of callers catch it: the renderer's (IndexError) and the metrics' (ValueError)
    assert issubclass(FaceIndexError, IndexError) and issubclass(FaceIndexError, ValueError)
    with pytest.raises(FaceIndexError, match=r"got range \[-1, 2\]"):
        check_faces(torch.tensor([[-1, 1, 2]]), 4)


@pytest.mark.parametrize("renderer", list_renderers())
@pytest.mark.parametrize("dtype", [torch.int16, torch.int32, torch.uint8])
def test_any_integer_faces(dtype: torch.dtype, renderer: str) -> None:
    # faces of any integer dtype that the checks accept index the same vertices as int64 ones: same images
    verts, faces = ellipsoid(1, scale=0.6)  # 42 vertices: uint8 holds the indices
    verts = verts[None].repeat(2, 1, 1)
    R, T = look_at_view_transform(2.7, 20.0, torch.tensor([0.0, 130.0]))
    colors = TexturesVertex(torch.rand(2, verts.shape[1], 3, generator=torch.Generator().manual_seed(0)))
    check_mesh(verts, faces.to(dtype))
    render = build_renderer(renderer, image_size=24)
    expected = render(verts, faces, colors, R=R, T=T)
    assert expected[:, -1].sum() > 50  # the meshes are in view
    assert torch.equal(render(verts, faces.to(dtype), colors, R=R, T=T), expected)
    with pytest.raises(FaceIndexError, match=r"got range \[0, 42\]"):
        check_mesh(verts, torch.cat([faces, torch.tensor([[0, 1, 42]])]).to(dtype))


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


def test_check_shape_binds_symbolic_dimensions() -> None:
    dims = check_shape(torch.zeros(4, 7, 3), "B, V, 3", "verts")
    assert dims == {"B": 4, "V": 7}
    check_shape(torch.zeros(4, 5), "B C", "codes", dims)  # same B, new C
    assert dims == {"B": 4, "V": 7, "C": 5}
    with pytest.raises(ShapeError, match=r"^textures must have shape \(4, 2\), got \(3, 2\)$"):
        check_shape(torch.zeros(3, 2), "B, 2", "textures", dims)
    with pytest.raises(ShapeError, match=r"square must have shape \(N, N\), got \(2, 3\)"):
        check_shape(torch.zeros(2, 3), "N N", "square")  # a name recurring within one tensor


@pytest.mark.parametrize(
    ("shape", "good", "bad"),
    [
        ("B, 3", (2, 3), (2, 4)),
        ("*, 3, 3", (5, 2, 3, 3), (3, 4)),
        ("*, 6", (6,), (2, 5)),
        ("F, 3", (0, 3), (3,)),
    ],
)
def test_check_shape_contracts(shape: str, good: tuple[int, ...], bad: tuple[int, ...]) -> None:
    check_shape(torch.zeros(good), shape, "x")
    with pytest.raises(ShapeError, match=rf"got {re.escape(str(bad))}"):
        check_shape(torch.zeros(bad), shape, "x")


def test_check_shape_type_errors() -> None:
    with pytest.raises(TypeError, match="x must be a torch.Tensor, got list"):
        check_shape([1, 2, 3], "N", "x")
    with pytest.raises(TypeError, match="x must be a floating point tensor, got torch.int64"):
        check_shape(torch.zeros(2, dtype=torch.int64), "N", "x", floating=True)
    with pytest.raises(ValueError, match="bad shape contract"):
        check_shape(torch.zeros(2), "N, *", "x")  # '*' only leads
    assert issubclass(ShapeError, ValueError)  # callers that catch ValueError keep working


def test_check_shape_alternatives_bind_the_first_that_matches() -> None:
    contract = "B, H, W | B, 1, H, W"
    assert check_shape(torch.zeros(2, 1, 5, 6), contract, "mask") == {"B": 2, "H": 5, "W": 6}
    assert check_shape(torch.zeros(2, 5, 6), contract, "mask") == {"B": 2, "H": 5, "W": 6}
    with pytest.raises(ShapeError, match=r"^mask must have shape \(B, H, W\) or \(B, 1, H, W\), got \(2, 3, 5, 6\)$"):
        check_shape(torch.zeros(2, 3, 5, 6), contract, "mask")
    dims = {"B": 3}
    with pytest.raises(ShapeError, match=r"must have shape \(3, H, W\) or \(3, 1, H, W\), got \(2, 5, 6\)"):
        check_shape(torch.zeros(2, 5, 6), contract, "mask", dims)
    assert dims == {"B": 3}  # a failed check binds nothing


def test_check_shape_named_leading_group() -> None:
    dims = check_shape(torch.zeros(4, 7, 2), "*N, 2", "pred")
    assert dims == {"N": (4, 7)}
    check_shape(torch.zeros(4, 7), "*N", "valid", dims)
    check_shape(torch.zeros(2), "*M, 2", "point")  # an empty group
    with pytest.raises(ShapeError, match=r"^valid must have shape \(4, 7\), got \(4, 6\)$"):
        check_shape(torch.zeros(4, 6), "*N", "valid", dims)
    with pytest.raises(ShapeError, match=r"^gt must have shape \(4, 7, 2\), got \(7, 2\)$"):
        check_shape(torch.zeros(7, 2), "*N, 2", "gt", dims)
    with pytest.raises(ShapeError, match=r"^pred must have shape \(\.\.\., 2\), got \(3,\)$"):
        check_shape(torch.zeros(3), "*N, 2", "pred")
    with pytest.raises(ValueError, match="bad shape contract"):
        check_shape(torch.zeros(2), "N, *M", "x")
