import math

import pytest
import torch
import trimesh

from unicorn.metrics.voxels import mesh_voxel_iou, voxel_centers, voxel_iou, voxelize_mesh


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
