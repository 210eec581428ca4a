"""Exported meshes reload in trimesh with the same vertices, UVs and texture."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from unicorn.model import Unicorn, export_prediction, save_mesh

from .helpers import randomize_heads, tiny_config


@pytest.fixture(scope="module")
def model_and_prediction():
    torch.manual_seed(0)
    model = Unicorn(tiny_config())
    randomize_heads(model, std=0.05)
    model.set_active_dims(shape=4, texture=16)
    with torch.no_grad():
        pred = model.predict(torch.rand(2, 3, 32, 32))
    return model, pred


def _texture_pixels(mesh: trimesh.Trimesh) -> np.ndarray:
    material = mesh.visual.material
    image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    return np.asarray(image.convert("RGB"))


@pytest.mark.parametrize("posed", [False, True])
@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_export_roundtrip(model_and_prediction, tmp_path, posed, suffix):
    model, pred = model_and_prediction
    mesh = export_prediction(model, pred, index=1, posed=posed)
    verts = pred.verts[1] @ pred.R[1] + pred.T[1] if posed else pred.verts[1]
    # seam and pole vertices are duplicated, nothing else changes
    assert len(mesh.vertices) > 642 and len(mesh.faces) == 1280
    # same point sets (rounding then np.unique would split values that straddle a rounding boundary)
    dist = np.linalg.norm(mesh.vertices[:, None] - verts.numpy()[None].astype(np.float64), axis=-1)
    assert dist.min(axis=1).max() < 1e-6 and dist.min(axis=0).max() < 1e-6
    corners = mesh.vertices[mesh.faces]
    assert np.allclose(corners, verts.numpy()[model.template.faces.numpy()], atol=1e-6)
    assert np.allclose(mesh.visual.uv[mesh.faces], model.template.face_uvs.numpy(), atol=1e-6)
    expected_texture = (pred.texture[1].clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy()
    files = save_mesh(mesh, tmp_path / f"pred{suffix}")
    if suffix == ".obj":
        assert {f.name for f in files} == {"pred.obj", "pred.mtl", "pred.png"}
    loaded = trimesh.load(files[0], force="mesh", process=False)
    assert loaded.vertices.shape == mesh.vertices.shape
    assert np.allclose(loaded.vertices, mesh.vertices, atol=1e-6)
    assert np.array_equal(loaded.faces, mesh.faces)
    assert np.allclose(loaded.visual.uv, mesh.visual.uv, atol=1e-6)
    assert np.array_equal(_texture_pixels(loaded), expected_texture)


def test_reference_uvs_are_converted_to_edge_convention():
    torch.manual_seed(0)
    model = Unicorn(tiny_config(template={"uv_mode": "reference"})).eval()
    with torch.no_grad():
        pred = model.predict(torch.rand(1, 3, 32, 32))
    mesh = export_prediction(model, pred)
    W = pred.texture.shape[-1]
    uv = model.template.face_uvs.numpy()
    assert np.allclose(mesh.visual.uv[mesh.faces], (uv * (W - 1) + 0.5) / W, atol=1e-6)
    with pytest.raises(ValueError, match="unsupported"):
        save_mesh(mesh, "mesh.ply")
