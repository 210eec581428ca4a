"""Export predictions as textured triangle meshes (trimesh objects, OBJ + MTL + PNG, GLB).

Materials are unlit-neutral: base colour (glTF ``baseColorFactor``, MTL ``Kd``) exactly 1, so that viewers,
which multiply the texture by it, show the predicted texture unchanged; no specular term, fully rough. Both files
carry smooth vertex normals (:func:`smooth_normals`): without them glTF viewers must shade each face flat, and many
OBJ viewers do.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import trimesh
from PIL import Image

from unicorn.checks import check_shape
from unicorn.folders import make_parent_folders
from unicorn.io.serialization import remove_stale_temporaries, replacing

if TYPE_CHECKING:
    from unicorn.model.autoencoder import Prediction, Unicorn

__all__ = ["export_prediction", "glb_bytes", "neutral_material", "save_mesh", "smooth_normals", "textured_mesh"]

_WHITE = np.full(4, 255, dtype=np.uint8)


def neutral_material(image: Image.Image, name: str = "texture") -> trimesh.visual.material.PBRMaterial:
    """A glTF metallic-roughness material that shows ``image`` as is: base colour 1, not metallic, fully rough.

    (trimesh's ``SimpleMaterial`` defaults to a diffuse colour of 0.4, which viewers multiply the texture by.)
    """
    return trimesh.visual.material.PBRMaterial(
        name=name, baseColorTexture=image, baseColorFactor=_WHITE, metallicFactor=0.0, roughnessFactor=1.0
    )


def textured_mesh(
    verts: torch.Tensor,
    faces: torch.Tensor,
    face_uvs: torch.Tensor,
    texture: torch.Tensor,
    align_corners: bool = False,
    name: str = "texture",
) -> trimesh.Trimesh:
    """A trimesh mesh with per-vertex UVs and a texture image.

    trimesh (like glTF) needs one UV per vertex, so every vertex is duplicated once per distinct UV it takes in
    the per-face UVs (the seam column and the pole fans); the copies share their position exactly, so
    ``mesh.merge_vertices(merge_tex=True)`` gives back the template's closed surface, and :func:`save_mesh`
    writes OBJ files with one position per template vertex (watertight). Seam-fixed UVs may have ``u > 1``:
    OBJ and glTF viewers repeat textures by default, which is the wrap the renderer used. ``v`` runs bottom
    to top in both our UVs and OBJ/glTF (trimesh converts for glTF), so UVs are written unchanged.

    Args:
        verts: (V, 3) vertices.
        faces: (F, 3) faces.
        face_uvs: (F, 3, 2) UVs of every face corner.
        texture: (3, Ht, Wt) image in [0, 1].
        align_corners: the UVs address texel centres at the borders (``u * (Wt - 1)``, the released models'
            sampling); they are converted to the file formats' edge convention.
        name: material (and texture file) name.

    Returns:
        ``trimesh.Trimesh`` (not processed: vertex order kept) with ``TextureVisuals``.
    """
    check_shape(verts, "V, 3", "verts")
    dims = check_shape(faces, "F, 3", "faces")
    check_shape(face_uvs, "F, 3, 2", "face_uvs", dims)
    check_shape(texture, "3, Ht, Wt", "texture")
    v = verts.detach().cpu().double().numpy()
    f = faces.detach().cpu().numpy().astype(np.int64)
    uv = face_uvs.detach().cpu().double().numpy().reshape(-1, 2)
    if align_corners:
        H, W = texture.shape[1:]
        uv = np.stack([(uv[:, 0] * (W - 1) + 0.5) / W, (uv[:, 1] * (H - 1) + 0.5) / H], axis=1)
    corners = np.concatenate([f.reshape(-1, 1).astype(np.float64), np.round(uv, 9)], axis=1)
    unique, inverse = np.unique(corners, axis=0, return_inverse=True)
    new_verts = v[unique[:, 0].astype(np.int64)]
    new_faces = inverse.reshape(-1, 3)
    pixels = (texture.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    image = Image.fromarray(np.ascontiguousarray(pixels), mode="RGB")
    material = neutral_material(image, name)
    visual = trimesh.visual.TextureVisuals(uv=unique[:, 1:], image=image, material=material)
    return trimesh.Trimesh(new_verts, new_faces, visual=visual, process=False)


def export_prediction(
    model: Unicorn, prediction: Prediction, index: int = 0, posed: bool = False, name: str = "texture"
) -> trimesh.Trimesh:
    """The textured mesh of one predicted instance.

    Args:
        model: the model that made the prediction (for the template's faces and UVs).
        prediction: output of :meth:`Unicorn.predict`.
        index: which instance of the batch.
        posed: False: world (canonical object) frame, ``scale * (template + displacement)``; True: camera
            view frame of the most likely pose, ``x @ R + T`` (PyTorch3D view axes: +X left, +Y up, +Z away
            from the camera).
        name: material name.
    """
    verts = prediction.verts[index]
    if posed:
        verts = verts @ prediction.R[index] + prediction.T[index]
    tmpl = model.template
    return textured_mesh(
        verts, tmpl.faces, tmpl.face_uvs, prediction.texture[index], align_corners=not tmpl.wrap_u, name=name
    )


def save_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike, overwrite: bool = False) -> list[Path]:
    """Write ``mesh`` to ``path``: ``.obj`` (with ``<stem>.mtl`` and ``<stem>.png`` beside it) or ``.glb``.

    The OBJ keeps positions and UVs apart (``f v/vt``): vertices that :func:`textured_mesh` split only for
    their UVs are written once, so the surface stays closed. Both formats get a material of base colour 1
    (MTL ``Kd 1 1 1``, glTF ``baseColorFactor [1, 1, 1, 1]``) whatever ``mesh``'s material says, so that the
    texture is shown unchanged.

    Args:
        mesh: a textured mesh (:func:`textured_mesh`, :func:`export_prediction`).
        path: the ``.obj`` or ``.glb`` file (``~`` is the home folder; missing folders are created).
        overwrite: replace files that exist; otherwise an existing file among those written (the OBJ's texture
            ``<stem>.png`` may be the photo the mesh was made from) is an error and nothing is written. Each file
            is written beside its place (``.<name>.tmp-<pid>``) and renamed into it: a file replaced is whole, the
            old one or the new; such temporaries that a killed save of the same files left are deleted.

    Returns:
        the files written (the OBJ and MTL in UTF-8).

    Raises:
        ValueError: another format, or a mesh without texture.
        FileExistsError: a file to write exists and ``overwrite`` is False (the message names it).
        IsADirectoryError: a folder is where a file to write goes, whatever ``overwrite`` (nothing is written).
        NotADirectoryError: a file stands where a folder above ``path`` goes (the message names it).
    """
    path = Path(path).expanduser()  # as load_model and save_model do: "~/car.glb" is not ./~/car.glb
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".obj"):
        raise ValueError(f"unsupported mesh format {path.suffix!r}: use .obj or .glb")
    image = _texture_image(mesh)
    targets = [path] if suffix == ".glb" else _obj_files(path)
    names = ", ".join(p.name for p in targets)
    folder = next((p for p in targets if p.is_dir() and not p.is_symlink()), None)  # a link is replaced, not followed
    if folder is not None:  # refused before anything is written: no file of the set replaced
        raise IsADirectoryError(f"{folder} is a folder: save_mesh writes {names}; choose another path")
    existing = [p for p in targets if p.exists() or p.is_symlink()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing[0]} exists: save_mesh writes {names}; pass overwrite=True to replace them")
    make_parent_folders(path)
    remove_stale_temporaries(path.parent, [p.name for p in targets])  # what a save to ``path`` killed left
    if suffix == ".glb":
        with replacing(path) as tmp:
            tmp.write_bytes(glb_bytes(mesh, name=path.stem))
        return [path]
    return _write_obj(mesh, image, path)


def glb_bytes(mesh: trimesh.Trimesh, name: str = "texture") -> bytes:
    """The binary glTF of a textured ``mesh``, with a material of base colour 1 (see :func:`save_mesh`)."""
    image = _texture_image(mesh)
    normals = smooth_normals(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    mesh = mesh.copy()
    mesh.visual.material = neutral_material(image, getattr(mesh.visual.material, "name", None) or name)
    mesh.vertex_normals = normals
    return mesh.export(file_type="glb", include_normals=True)


def _weld(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct positions of (V, 3) ``vertices`` in first-seen order (for an export, the template's vertex
    order), and each vertex's index among them, (V,): copies made for the UVs have bit-identical positions."""
    positions, index = np.unique(np.asarray(vertices), axis=0, return_inverse=True)
    index = index.reshape(-1)
    first = np.full(len(positions), len(index), dtype=np.int64)
    np.minimum.at(first, index, np.arange(len(index)))
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return positions[order], rank[index]


def smooth_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals of the surface ``vertices`` and ``faces`` describe, (V, 3) float32.

    Each is the area-weighted mean of the normals of the faces around its position: vertices at the same position
    (the copies :func:`textured_mesh` makes along the texture seam) get the same normal, so that shading is
    smooth across the seam. Faces wind counter-clockwise seen from outside, as the template's do: normals point
    out. A position without area around it gets +Z.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices.
    """
    positions, index = _weld(vertices)
    return _welded_normals(positions, index[np.asarray(faces, dtype=np.int64)])[index]


def _welded_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """:func:`smooth_normals` of (P, 3) distinct ``positions`` and (F, 3) ``faces`` indexing them: (P, 3) float32."""
    corners = positions[faces]  # (F, 3, 3)
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # length: twice the area
    summed = np.zeros_like(positions)
    np.add.at(summed, faces.reshape(-1), np.repeat(face_normals, 3, axis=0))
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    flat = length[:, 0] == 0
    summed[flat], length[flat] = (0.0, 0.0, 1.0), 1.0
    return (summed / length).astype(np.float32)


def _texture_image(mesh: trimesh.Trimesh) -> Image.Image:
    visual = mesh.visual
    material = getattr(visual, "material", None)
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    if not isinstance(visual, trimesh.visual.TextureVisuals) or visual.uv is None or image is None:
        raise ValueError("save_mesh needs a textured mesh (TextureVisuals with UVs and an image)")
    return image.convert("RGB")


def _write_obj(mesh: trimesh.Trimesh, image: Image.Image, path: Path) -> list[Path]:
    positions, position_index = _weld(np.asarray(mesh.vertices))  # one position (and normal) per template vertex
    faces = np.asarray(mesh.faces, dtype=np.int64)
    normals = _welded_normals(positions, position_index[faces])
    uv = np.asarray(mesh.visual.uv, dtype=np.float64)
    stem = path.stem
    lines = [f"# unicorn textured mesh: {len(positions)} vertices, {len(faces)} faces", f"mtllib {stem}.mtl"]
    lines += [f"v {x:.8g} {y:.8g} {z:.8g}" for x, y, z in positions]
    lines += [f"vt {u:.8g} {v:.8g}" for u, v in uv]
    lines += [f"vn {x:.6g} {y:.6g} {z:.6g}" for x, y, z in normals]
    lines.append(f"usemtl {stem}")
    v_idx, t_idx = position_index[faces] + 1, faces + 1  # OBJ indices start at 1; normals share the positions'
    lines += [
        f"f {a}/{ta}/{a} {b}/{tb}/{b} {c}/{tc}/{c}" for (a, b, c), (ta, tb, tc) in zip(v_idx.tolist(), t_idx.tolist())
    ]
    mtl = "\n".join(
        [
            f"newmtl {stem}",
            "Ka 0 0 0",
            "Kd 1 1 1",  # viewers multiply the texture by Kd
            "Ks 0 0 0",
            "d 1",
            "illum 1",
            f"map_Kd {stem}.png",
            "",
        ]
    )
    obj, mtl_path, png = _obj_files(path)
    # each file whole or as it was (an overwritten one too); the texture first, the OBJ that names it last
    with replacing(png) as tmp:
        image.save(tmp, format="PNG")
    with replacing(mtl_path) as tmp:
        tmp.write_text(mtl, encoding="utf-8")  # whatever the locale: viewers read file names in UTF-8
    with replacing(obj) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return [obj, mtl_path, png]


def _obj_files(path: Path) -> list[Path]:
    """The OBJ, its material file and its texture, which :func:`save_mesh` writes side by side."""
    return [path, path.with_suffix(".mtl"), path.with_suffix(".png")]
