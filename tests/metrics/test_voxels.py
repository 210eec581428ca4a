import math

import pytest
import torch
import trimesh

from unicorn.metrics.voxels import (
    mesh_voxel_iou,
    point_cloud_voxel_iou,
    voxel_centers,
    voxel_iou,
    voxelize_mesh,
    voxelize_points,
)


def box(extents, offset=(0.0, 0.0, 0.0)):
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(offset)
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces)


def test_centres():
    torch.testing.assert_close(voxel_centers(4), torch.tensor([-0.375, -0.125, 0.125, 0.375]))


def test_box_voxel_count_and_offset_cubes_iou():
    v, f = box((0.5, 0.5, 0.5))
    occ = voxelize_mesh(v, f)
    assert occ.shape == (32, 32, 32) and int(occ.sum()) == 16**3
    assert occ[8:24, 8:24, 8:24].all()
    v2, f2 = box((0.5, 0.5, 0.5), (0.25, 0.0, 0.0))
    # overlap 0.25 x 0.5 x 0.5 over union 2 * 0.125 - 0.0625: exactly 1/3 (faces fall between cell centres)
    assert mesh_voxel_iou(v[None], f, v2[None], f2).item() == pytest.approx(1 / 3, abs=1e-12)


def test_self_iou_and_sphere_volume(blob):
    v, f = blob
    occ = voxelize_mesh(torch.stack([v, 0.8 * v]), f)
    assert occ.shape == (2, 32, 32, 32)
    torch.testing.assert_close(voxel_iou(occ, occ), torch.ones(2, dtype=torch.float64))
    assert 0.3 < voxel_iou(occ[0], occ[1]).item() < 0.8
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    occ = voxelize_mesh(torch.tensor(sphere.vertices), torch.tensor(sphere.faces), resolution=48)
    assert float(occ.sum()) / 48**3 == pytest.approx(sphere.volume, rel=0.03)
    assert sphere.volume == pytest.approx(4 / 3 * math.pi * 0.4**3, rel=0.02)


def test_thin_plate_needs_surface_samples():
    v, f = box((0.5, 0.5, 0.01))
    assert int(voxelize_mesh(v, f).sum()) == 0
    assert int(voxelize_mesh(v, f, surface_samples=20000).sum()) >= 2 * 16 * 16


def test_voxel_iou_edge_cases():
    empty = torch.zeros(4, 4, 4, dtype=torch.bool)
    assert voxel_iou(empty, empty).item() == 1.0
    with pytest.raises(ValueError, match="share"):
        voxel_iou(empty, torch.zeros(2, 4, 4, 4, dtype=torch.bool))


def test_occupancy_of_an_octahedron_is_exact():
    """Planar faces make the inside test analytic: |x| + |y| + |z| < r, cell centre by cell centre."""
    r = 0.4123
    verts = torch.tensor([[r, 0, 0], [-r, 0, 0], [0, r, 0], [0, -r, 0], [0, 0, r], [0, 0, -r]], dtype=torch.float64)
    hull = trimesh.convex.convex_hull(verts.numpy())
    occ = voxelize_mesh(torch.tensor(hull.vertices), torch.tensor(hull.faces), resolution=20)
    c = voxel_centers(20, dtype=torch.float64)
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    expected = x.abs() + y.abs() + z.abs() < r
    assert occ.sum() > 500 and torch.equal(occ, expected)


# --- surface point clouds (the evaluation's iou-3d columns) ---------------------------------------------------------


def sphere_points(radius: float, n: int, centre=(0.0, 0.0, 0.0), seed: int = 0) -> torch.Tensor:
    """(n, 3) area-uniform points on a sphere (normalised Gaussian directions)."""
    v = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return radius * v / v.norm(dim=1, keepdim=True) + torch.tensor(centre, dtype=torch.float64)


def cells_meeting_ball(radius: float, resolution: int, bounds=(-0.5, 0.5), centre=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """The oracle: (R, R, R) cells whose closed box comes within ``radius`` of the centre (analytic, per axis)."""
    lo, hi = bounds
    edges = lo + torch.arange(resolution + 1, dtype=torch.float64) * (hi - lo) / resolution
    nearest = []  # per axis, each cell's squared distance from the centre's coordinate
    for c in centre:
        a, b = edges[:-1] - c, edges[1:] - c
        nearest.append(torch.where(a > 0, a, torch.where(b < 0, b, torch.zeros_like(a))) ** 2)
    x, y, z = torch.meshgrid(*nearest, indexing="ij")
    return x + y + z <= radius**2


def box_points(first: tuple[int, int, int], last: tuple[int, int, int], resolution: int, n: int) -> torch.Tensor:
    """Surface points of the box whose faces cut cells ``first`` .. ``last`` (per axis) through their middles."""
    h = 1.0 / resolution
    a = -0.5 + (torch.tensor(first, dtype=torch.float64) + 0.5) * h
    b = -0.5 + (torch.tensor(last, dtype=torch.float64) + 0.5) * h
    m = trimesh.creation.box(extents=(b - a).tolist())
    m.apply_translation(((a + b) / 2).tolist())
    return torch.tensor(trimesh.sample.sample_surface(m, n, seed=0)[0])


def test_boxes_fill_the_cells_they_cut_and_their_iou_is_the_analytic_one():
    """Faces through cell middles: the solid is exactly the cells first..last, i.e. the box grown by h/2 a side."""
    R = 32
    boxes = [((6, 8, 10), (21, 23, 19)), ((12, 4, 10), (27, 19, 25))]
    clouds = [box_points(first, last, R, 100_000) for first, last in boxes]
    for cloud, (first, last) in zip(clouds, boxes):
        expected = torch.zeros(R, R, R, dtype=torch.bool)
        expected[first[0] : last[0] + 1, first[1] : last[1] + 1, first[2] : last[2] + 1] = True
        assert torch.equal(voxelize_points(cloud, R), expected)
    # analytic IoU of the two boxes grown by half a cell on every face (lengths in cells)
    (f1, l1), (f2, l2) = boxes
    vol1 = math.prod(b - a + 1 for a, b in zip(f1, l1))
    vol2 = math.prod(b - a + 1 for a, b in zip(f2, l2))
    inter = math.prod(max(0, min(b1, b2) - max(a1, a2) + 1) for a1, b1, a2, b2 in zip(f1, l1, f2, l2))
    iou = point_cloud_voxel_iou(clouds[0][None], clouds[1][None], R)
    assert iou.shape == (1,) and iou.dtype == torch.float64
    assert iou.item() == pytest.approx(inter / (vol1 + vol2 - inter), abs=1e-12)


def test_concentric_spheres_match_the_cell_oracle_and_approach_the_analytic_iou():
    """IoU of concentric balls r1 < r2 is (r1 / r2)^3; on the grid each solid is the cells meeting its ball (the
    oracle), up to cells that the sphere only clips at a corner, which a finite sample can miss."""
    r1, r2 = 0.3, 0.45
    errors = {}
    for R in (32, 128):
        inner, outer = sphere_points(r1, 200_000), sphere_points(r2, 200_000, seed=1)
        if R == 32:
            for r, cloud in ((r1, inner), (r2, outer)):
                occ, oracle = voxelize_points(cloud, R), cells_meeting_ball(r, R)
                assert not (occ & ~oracle).any()  # never a cell the ball does not meet
                assert (oracle & ~occ).sum() <= 0.01 * oracle.sum()  # corner clips only
            oracle_iou = voxel_iou(cells_meeting_ball(r1, R), cells_meeting_ball(r2, R)).item()
            assert point_cloud_voxel_iou(inner[None], outer[None], R).item() == pytest.approx(oracle_iou, abs=0.005)
        iou = point_cloud_voxel_iou(inner[None], outer[None], R).item()
        # cells meeting a ball of radius r lie between it and the ball of radius r + sqrt(3) h (a cell diagonal),
        # and the inner solid lies inside the outer one, so IoU = |inner| / |outer| is bounded by:
        d = math.sqrt(3) / R
        assert (r1 / (r2 + d)) ** 3 <= iou <= ((r1 + d) / r2) ** 3
        errors[R] = abs(iou - (r1 / r2) ** 3)
    assert errors[128] < 0.3 * errors[32]  # the voxel error shrinks with the cell size (here by 4x)


def test_a_prediction_outside_the_cube_counts_in_the_union():
    """The grid extends beyond the unit cube with the same cells: the oracle on a 3x wider grid gives the IoU."""
    gt, pred = sphere_points(0.3, 100_000), sphere_points(0.3, 100_000, centre=(0.35, 0.0, 0.0), seed=1)
    iou = point_cloud_voxel_iou(pred[None], gt[None]).item()
    wide = dict(resolution=96, bounds=(-1.5, 1.5))  # cells of side 1/32 aligned with the cube's
    oracle = voxel_iou(cells_meeting_ball(0.3, **wide, centre=(0.35, 0.0, 0.0)), cells_meeting_ball(0.3, **wide))
    assert iou == pytest.approx(oracle.item(), abs=0.005)
    # cropped to the cube, the part sticking out would be lost from the union
    assert voxel_iou(voxelize_points(pred), voxelize_points(gt)).item() > iou + 0.01


def test_sparse_clouds_are_closed_and_open_surfaces_stay_hollow():
    # 5k points on a 0.45 sphere leave gaps in the shell that a plain flood fill leaks through; the closing seals them
    occ, oracle = voxelize_points(sphere_points(0.45, 5_000)), cells_meeting_ball(0.45, 32)
    assert voxel_iou(occ, oracle).item() > 0.94 and occ[16, 16, 16]
    # a box without its top face: nothing encloses the inside, only the surface cells are occupied
    m = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    m.update_faces(m.face_normals[:, 2] < 0.5)
    cup = voxelize_points(torch.tensor(trimesh.sample.sample_surface(m, 100_000, seed=0)[0]))
    assert not cup[16, 16, 16] and cup.sum() < 0.5 * 17**3


def test_point_cloud_shapes_and_errors():
    cloud = sphere_points(0.3, 20_000)
    batched = voxelize_points(torch.stack([cloud, 0.5 * cloud]), 16)
    assert batched.shape == (2, 16, 16, 16) and torch.equal(batched[0], voxelize_points(cloud, 16))
    assert point_cloud_voxel_iou(cloud[None], cloud[None]).item() == 1.0
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        point_cloud_voxel_iou(cloud, cloud)
    with pytest.raises(ValueError, match=r"^points must have shape \(B, P, 3\) or \(P, 3\), got \(20000, 2\)$"):
        voxelize_points(cloud[:, :2])
