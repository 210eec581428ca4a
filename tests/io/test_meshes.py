"""Exported meshes reload in trimesh and open3d with the same vertices, UVs and texture, and show its colours."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from tests.support.model import randomize_heads, tiny_config
from unicorn.io import export_prediction, save_mesh
from unicorn.io.meshes import smooth_normals, textured_mesh
from unicorn.model import Unicorn
from unicorn.render.textures import sample_bilinear


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
    # seam and pole vertices are duplicated for their UVs, at bit-identical positions
    assert len(mesh.vertices) > 642 and len(mesh.faces) == 1280
    welded = mesh.copy()
    welded.merge_vertices(merge_tex=True, merge_norm=True)
    assert len(welded.vertices) == 642 and welded.is_watertight
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
    # which seam copy comes first is trimesh's (an unstable argsort of the OBJ's (v, vt) pairs): compare corners
    assert np.allclose(loaded.vertices[loaded.faces], mesh.vertices[mesh.faces], atol=1e-6)
    assert np.allclose(loaded.visual.uv[loaded.faces], mesh.visual.uv[mesh.faces], atol=1e-6)
    assert np.array_equal(_texture_pixels(loaded), expected_texture)


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_file_that_exists_is_replaced_only_when_asked(model_and_prediction, tmp_path, suffix):
    model, pred = model_and_prediction
    mesh = export_prediction(model, pred, index=0)
    photo = tmp_path / ("car.png" if suffix == ".obj" else f"car{suffix}")  # the OBJ's texture takes the photo's name
    photo.write_bytes(b"the user's photo")
    with pytest.raises(FileExistsError, match=rf"{re.escape(str(photo))} exists: save_mesh writes car{suffix}"):
        save_mesh(mesh, tmp_path / f"car{suffix}")
    assert sorted(p.name for p in tmp_path.iterdir()) == [photo.name]  # nothing written
    assert photo.read_bytes() == b"the user's photo"
    files = save_mesh(mesh, tmp_path / f"car{suffix}", overwrite=True)
    assert photo in files and photo.read_bytes() != b"the user's photo"


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_path_in_the_home_folder_is_written_there(model_and_prediction, tmp_path, monkeypatch, suffix):
    """``~/meshes/car.glb`` is a file in the home folder (as for save_model), not in a folder named ``~``."""
    model, pred = model_and_prediction
    home, cwd = tmp_path / "home", tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(cwd)
    files = save_mesh(export_prediction(model, pred, index=0), f"~/meshes/car{suffix}")
    assert files[0] == home / "meshes" / f"car{suffix}" and all(f.is_file() for f in files)
    assert list(cwd.iterdir()) == []


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_replacement_that_fails_leaves_each_file_as_it_was(model_and_prediction, tmp_path, monkeypatch, suffix):
    model, pred = model_and_prediction
    mesh = export_prediction(model, pred, index=0)
    files = save_mesh(mesh, tmp_path / f"car{suffix}")
    before = {path: path.read_bytes() for path in files}

    def full_disk(self, data):
        self.open("wb").write(data[: len(data) // 2])  # half the bytes, then the disk is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    monkeypatch.setattr(Path, "write_text", lambda self, text, **kwargs: full_disk(self, text.encode()))
    with pytest.raises(OSError, match="No space left"):
        save_mesh(mesh.copy(), tmp_path / f"car{suffix}", overwrite=True)
    assert {path: path.read_bytes() for path in files} == before  # whole: the old files
    assert sorted(tmp_path.iterdir()) == sorted(files)  # no partial file beside them


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
@pytest.mark.parametrize("below", ["", "meshes/"])
def test_a_file_where_a_folder_goes_is_named_in_one_line(model_and_prediction, tmp_path, suffix, below):
    model, pred = model_and_prediction
    notes = tmp_path / "notes"
    notes.write_text("the user's notes")
    path = notes / f"{below}car{suffix}"
    with pytest.raises(NotADirectoryError) as info:
        save_mesh(export_prediction(model, pred, index=0), path)
    assert str(info.value) == f"cannot write {path}: {notes} is a file, where a folder goes"
    assert notes.read_text() == "the user's notes" and sorted(tmp_path.iterdir()) == [notes]


@pytest.mark.parametrize("folder", ["car.obj", "car.png", "car.glb"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_where_a_file_goes_is_refused_before_anything_is_written(
    model_and_prediction, tmp_path, folder, overwrite
):
    model, pred = model_and_prediction
    (tmp_path / folder).mkdir()
    path = tmp_path / ("car.glb" if folder == "car.glb" else "car.obj")
    names = "car.glb" if folder == "car.glb" else "car.obj, car.mtl, car.png"
    with pytest.raises(IsADirectoryError) as info:
        save_mesh(export_prediction(model, pred, index=0), path, overwrite=overwrite)
    assert str(info.value) == f"{tmp_path / folder} is a folder: save_mesh writes {names}; choose another path"
    assert list(tmp_path.iterdir()) == [tmp_path / folder] and not any((tmp_path / folder).iterdir())


def _dead_pid() -> int:
    """The pid of a process that has ended."""
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_save_removes_the_temporaries_a_killed_save_of_its_files_left(model_and_prediction, tmp_path, suffix):
    model, pred = model_and_prediction
    dead, live = _dead_pid(), os.getppid()
    names = ["car.obj", "car.mtl", "car.png"] if suffix == ".obj" else ["car.glb"]
    stale = [tmp_path / f".{name}.tmp-{dead}" for name in names]
    kept = [
        tmp_path / f".{names[-1]}.tmp-{live}",  # a save running in another process
        tmp_path / f".{names[0]}.tmp-1.tmp-{dead}",  # the temporary of another file, ``car.obj.tmp-1``
        tmp_path / f".{names[0]}.tmp-{dead}.bak",  # not the pattern of a temporary
        tmp_path / f".bus{suffix}.tmp-{dead}",  # another mesh's
        tmp_path / f"{names[0]}.tmp-{dead}",  # not hidden: a user's file
    ]
    for path in stale + kept:
        path.write_bytes(b"partial")
    files = save_mesh(export_prediction(model, pred, index=0), tmp_path / f"car{suffix}")
    assert sorted(tmp_path.iterdir()) == sorted(files + kept)
    assert all(path.read_bytes() == b"partial" for path in kept)


def test_a_name_beyond_ascii_is_written_in_utf8_and_reloads(model_and_prediction, tmp_path):
    model, pred = model_and_prediction
    mesh = export_prediction(model, pred, index=0)
    obj, mtl, png = save_mesh(mesh, tmp_path / "voiture_été_车.obj")
    assert mtl.name == "voiture_été_车.mtl" and png.name == "voiture_été_车.png"
    assert "mtllib voiture_été_车.mtl\n" in obj.read_bytes().decode("utf-8")
    assert "map_Kd voiture_été_车.png\n" in mtl.read_bytes().decode("utf-8")
    loaded = trimesh.load(obj, force="mesh", process=False)  # finds the material and texture by their names
    assert np.array_equal(_texture_pixels(loaded), _texture_pixels(mesh))


def test_obj_and_mtl_do_not_depend_on_the_locale_encoding(tmp_path):
    """Text written in the locale's encoding (cp1252 on Windows, Latin-1 locales) would give other bytes for a name
    beyond ASCII, or fail: with ``-X warn_default_encoding`` every such write warns, made an error around the save
    (the imports' own warnings ignored)."""
    script = (
        "import sys, warnings, torch\n"
        "from unicorn.io.meshes import save_mesh, textured_mesh\n"
        "mesh = textured_mesh(torch.eye(3), torch.tensor([[0, 1, 2]]), torch.rand(1, 3, 2), torch.rand(3, 4, 4))\n"
        "with warnings.catch_warnings():\n"
        "    warnings.simplefilter('error', EncodingWarning)\n"
        "    save_mesh(mesh, sys.argv[1])\n"
    )
    done = subprocess.run(
        [
            sys.executable,
            "-X",
            "warn_default_encoding",
            "-W",
            "ignore::EncodingWarning",
            "-c",
            script,
            str(tmp_path / "voiture_é.obj"),
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "voiture_é.mtl").read_text(encoding="utf-8").startswith("newmtl voiture_é\n")


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


REPO = Path(__file__).resolve().parents[2]


def _sample_image(image: np.ndarray, uv: np.ndarray, rows_from_top: bool) -> np.ndarray:
    """Bilinear texel lookup as a glTF / OBJ viewer does it: texel centres at (i + 0.5) / size, u repeats.

    Rows are clamped (as the renderer does); ``rows_from_top``: row 0 is ``v = 1`` (PNG order).
    """
    H, W = image.shape[:2]
    x = uv[:, 0] * W - 0.5
    y = ((1.0 - uv[:, 1]) if rows_from_top else uv[:, 1]) * H - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    xs = [x0.astype(int) % W, (x0.astype(int) + 1) % W]
    ys = [np.clip(y0.astype(int), 0, H - 1), np.clip(y0.astype(int) + 1, 0, H - 1)]
    img = image.astype(np.float64) / 255.0
    top = img[ys[0], xs[0]] * (1 - fx) + img[ys[0], xs[1]] * fx
    bottom = img[ys[1], xs[0]] * (1 - fx) + img[ys[1], xs[1]] * fx
    return top * (1 - fy) + bottom * fy


def _model_colours(model: Unicorn, texture: torch.Tensor) -> np.ndarray:
    """(F, 3) what the model's renderer shows at every face centre: its own sampler on the predicted texture."""
    tmpl = model.template
    uv = tmpl.face_uvs.mean(1)
    out = sample_bilinear(
        texture[None].clamp(0, 1), torch.zeros(len(uv), dtype=torch.long), uv, tmpl.wrap_u, not tmpl.wrap_u
    )
    return out.double().numpy()


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_exports_show_the_predicted_texture(model_and_prediction, tmp_path, suffix):
    """Viewers multiply the texture by the base colour: it must be 1, and colours must equal the model's."""
    model, pred = model_and_prediction
    files = save_mesh(export_prediction(model, pred, index=1), tmp_path / f"pred{suffix}")
    expected = _model_colours(model, pred.texture[1])
    tol = 1.0 / 255 + 1e-6  # the texture is stored as 8-bit

    # trimesh: material colour times the texture at every face's UV centre
    loaded = trimesh.load(files[0], force="mesh", process=False)
    material = loaded.visual.material
    factor = getattr(material, "baseColorFactor", None)
    if factor is None:  # OBJ: SimpleMaterial with Kd as `diffuse`
        factor = material.diffuse
    factor = np.asarray(factor, dtype=np.float64)[:3] / 255.0
    shown = factor * _sample_image(_texture_pixels(loaded), loaded.visual.uv[loaded.faces].mean(1), True)
    assert np.abs(shown - expected).max() < tol

    import open3d as o3d  # imported where used: the gpu tests run where open3d is not installed

    # open3d: the material of its renderer (read_triangle_model) and the mesh's per-corner UVs and texture
    model3d = o3d.io.read_triangle_model(str(files[0]))
    base = np.asarray(model3d.materials[0].base_color, dtype=np.float64)
    assert np.allclose(base, 1.0)
    mesh3d = o3d.io.read_triangle_mesh(str(files[0]))
    ids = np.asarray(mesh3d.triangle_material_ids)
    image = np.asarray(mesh3d.textures[ids[0]])  # open3d keeps image rows bottom (v = 0) first
    uv = np.asarray(mesh3d.triangle_uvs).reshape(-1, 3, 2).mean(1)
    # open3d may reorder faces: compare each face with the template face at the same position
    centres = np.asarray(mesh3d.vertices)[np.asarray(mesh3d.triangles)].mean(1)
    template_centres = pred.verts[1].double().numpy()[model.template.faces.numpy()].mean(1)
    order = np.linalg.norm(centres[:, None] - template_centres[None], axis=-1).argmin(1)
    shown = base[:3] * _sample_image(image, uv, False)
    assert np.abs(shown - expected[order]).max() < tol


def test_obj_is_welded(model_and_prediction, tmp_path):
    """The OBJ writes every template vertex once (positions and UVs indexed apart): a closed surface."""
    model, pred = model_and_prediction
    obj = save_mesh(export_prediction(model, pred, index=0), tmp_path / "welded.obj")[0]
    text = obj.read_text()
    positions = np.array([line.split()[1:] for line in text.splitlines() if line.startswith("v ")], dtype=float)
    faces = np.array(
        [[int(c.split("/")[0]) - 1 for c in line.split()[1:]] for line in text.splitlines() if line.startswith("f ")]
    )
    assert len(positions) == len(model.template.verts) == 642
    assert np.allclose(positions, pred.verts[0].double().numpy(), atol=1e-6)  # template order kept
    assert trimesh.Trimesh(positions, faces, process=False).is_watertight
    assert re.search(r"^Kd 1 1 1$", (tmp_path / "welded.mtl").read_text(), re.M)


def test_glb_passes_the_khronos_validator(model_and_prediction, tmp_path):
    """The Khronos glTF validator (npm package gltf-validator, installed by `npm ci`) finds no error or warning."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node.js is not installed: the Khronos glTF validator (npm gltf-validator) needs it")
    if not (REPO / "node_modules" / "gltf-validator").is_dir():
        pytest.fail("Node.js is present but gltf-validator is not installed: run `npm ci` in the repository root")
    model, pred = model_and_prediction
    glb = save_mesh(export_prediction(model, pred, index=1), tmp_path / "pred.glb")[0]
    script = Path(__file__).with_name("gltf_validate.cjs")
    result = subprocess.run([node, str(script), str(glb)], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    info = report["info"]
    assert info["drawCallCount"] == 1 and info["totalTriangleCount"] == 1280 and info["materialCount"] == 1


def _obj_normals(obj: Path) -> tuple[np.ndarray, np.ndarray]:
    """An OBJ's positions and, for each, the normal its face corners name (they must agree)."""
    lines = obj.read_text(encoding="utf-8").splitlines()
    positions = np.array([ln.split()[1:] for ln in lines if ln.startswith("v ")], dtype=float)
    normals = np.array([ln.split()[1:] for ln in lines if ln.startswith("vn ")], dtype=float)
    per_position = np.full_like(positions, np.nan)
    for ln in (ln for ln in lines if ln.startswith("f ")):
        for corner in ln.split()[1:]:
            v, _, n = (int(i) - 1 for i in corner.split("/"))
            assert np.isnan(per_position[v]).all() or np.array_equal(per_position[v], normals[n])
            per_position[v] = normals[n]
    return positions, per_position


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_exports_carry_smooth_outward_normals(model_and_prediction, tmp_path, suffix):
    """On the template ellipsoid each vertex's normal is the analytic one, ``(x / a^2, y / b^2, z / c^2)``, across
    the texture seam too."""
    model, _ = model_and_prediction
    tmpl = model.template
    mesh = textured_mesh(tmpl.verts, tmpl.faces, tmpl.face_uvs, torch.rand(3, 8, 16), align_corners=not tmpl.wrap_u)
    path = save_mesh(mesh, tmp_path / f"sphere{suffix}")[0]
    if suffix == ".obj":
        positions, normals = _obj_normals(path)
        assert len(positions) == 642  # one normal per welded position: the seam's copies share it
    else:
        loaded = trimesh.load(path, force="mesh", process=False)
        positions, normals = np.asarray(loaded.vertices), np.asarray(loaded.vertex_normals)
        assert len(positions) > 642  # the seam's copies, each with its normal
    axes = tmpl.verts.abs().amax(0).double().numpy()
    assert np.allclose(((positions / axes) ** 2).sum(1), 1.0, atol=1e-5)  # an ellipsoid of semi-axes ``axes``
    analytic = positions / axes**2
    analytic /= np.linalg.norm(analytic, axis=1, keepdims=True)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    error = np.degrees(np.arccos(np.clip((normals * analytic).sum(1), -1, 1)))
    assert error.max() < 8.0 and np.median(error) < 1.0  # outward, smooth (the discrete surface's few degrees)


def test_smooth_normals_weigh_faces_by_area():
    """A vertex shared by a large and a small face at a right angle leans towards the large face's normal."""
    verts = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 1], [0, -1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 3, 4]])  # the first: area 8, normal +Z; the second: area 0.5, normal +X
    normal = smooth_normals(verts, faces)[0]
    expected = np.array([0.5 * 2, 0, 8 * 2]) / np.linalg.norm([1, 0, 16])
    assert np.allclose(normal, expected, atol=1e-6)
    assert np.allclose(smooth_normals(verts, faces)[1], [0, 0, 1])
