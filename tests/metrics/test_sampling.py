import pytest
import torch
import trimesh

from unicorn.metrics.sampling import face_areas_normals, sample_points_from_meshes


def test_points_on_box_surface_with_outward_normals():
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    v = torch.tensor(box.vertices, dtype=torch.float32)
    f = torch.tensor(box.faces)
    p, n = sample_points_from_meshes(v[None], f, 20000, seed=0)
    half = torch.tensor([0.5, 1.0, 0.25])
    # on the surface: every point is inside the box and on one of its faces
    assert (p.abs() <= half + 1e-6).all()
    on_face = (p.abs() - half).abs() < 1e-5  # (1, N, 3)
    assert on_face.any(-1).all()
    # the normal is the outward axis of the face the point lies on
    axis = n.abs().argmax(-1)
    assert torch.gather(on_face, -1, axis.unsqueeze(-1)).all()
    assert (torch.sign(torch.gather(p, -1, axis.unsqueeze(-1))) == torch.gather(n, -1, axis.unsqueeze(-1))).all()
    # area weighting: share of points on the +-x faces = 2*(2*0.5) / total area
    areas = torch.tensor([2 * 0.5, 1 * 0.5, 1 * 2.0]) * 2
    share = torch.bincount(axis[0], minlength=3).float() / p.shape[1]
    torch.testing.assert_close(share, areas / areas.sum(), atol=0.015, rtol=0)


def test_sphere_points_and_normals(blob):
    mesh = trimesh.creation.icosphere(subdivisions=4)
    v, f = torch.tensor(mesh.vertices, dtype=torch.float64), torch.tensor(mesh.faces)
    p, n = sample_points_from_meshes(v, f, 5000, seed=1)
    assert p.shape == (5000, 3) and p.dtype == torch.float64
    assert (p.norm(dim=-1) - 1).abs().max() < 5e-3  # flat faces sit slightly inside the sphere
    assert torch.nn.functional.cosine_similarity(n, p, dim=-1).min() > 0.99


def test_seeded_reproducible_and_batched(blob):
    v, f = blob
    batch = torch.stack([v, 2 * v])
    p1, _ = sample_points_from_meshes(batch, f, 100, seed=3)
    p2, _ = sample_points_from_meshes(batch, f, 100, seed=3)
    p3, _ = sample_points_from_meshes(batch, f, 100, seed=4)
    assert torch.equal(p1, p2) and not torch.equal(p1, p3)
    assert p1.shape == (2, 100, 3)


def test_gradient_and_degenerate_mesh(blob):
    v, f = blob
    v = v.clone().requires_grad_(True)
    p, _ = sample_points_from_meshes(v, f, 50, seed=0)
    p.sum().backward()
    assert v.grad.abs().sum() > 0
    flat = torch.zeros(1, 4, 3)
    p, n = sample_points_from_meshes(flat, torch.tensor([[0, 1, 2], [0, 2, 3]]), 10, seed=0)
    assert torch.isfinite(p).all() and (n == 0).all()


def test_face_areas_normals():
    v = torch.tensor([[[0.0, 0, 0], [2, 0, 0], [0, 3, 0]]])
    a, n = face_areas_normals(v, torch.tensor([[0, 1, 2]]))
    assert a.item() == pytest.approx(3.0)
    torch.testing.assert_close(n, torch.tensor([[[0.0, 0, 1]]]))


def test_invalid_inputs(blob):
    v, f = blob
    with pytest.raises(ValueError, match="num_samples"):
        sample_points_from_meshes(v, f, 0)
    with pytest.raises(ValueError, match="face indices must be in"):
        sample_points_from_meshes(v, f + 10_000, 5)
    with pytest.raises(ValueError, match=r"\(F, 3\)"):
        sample_points_from_meshes(v, f[:, :2], 5)
    with pytest.raises(TypeError, match="integer"):
        sample_points_from_meshes(v, f.float(), 5)
