"""Export predictions as textured triangle meshes (trimesh objects, OBJ + MTL + PNG, GLB)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import trimesh
from PIL import Image

if TYPE_CHECKING:
    from unicorn.model.autoencoder import Prediction, Unicorn

__all__ = ["export_prediction", "save_mesh", "textured_mesh"]


def textured_mesh(
    verts: torch.Tensor,
    faces: torch.Tensor,
    face_uvs: torch.Tensor,
    texture: torch.Tensor,
    align_corners: bool = False,
    name: str = "texture",
) -> trimesh.Trimesh:
    """A trimesh mesh with per-vertex UVs and a texture image.

    trimesh (like OBJ and glTF) needs one UV per vertex, so every vertex is duplicated once per distinct UV
    it takes in the per-face UVs (the seam column and the pole fans). Seam-fixed UVs may have ``u > 1``:
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
    if verts.dim() != 2 or verts.shape[1] != 3 or faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"need verts (V, 3) and faces (F, 3), got {tuple(verts.shape)}, {tuple(faces.shape)}")
    if face_uvs.shape != (faces.shape[0], 3, 2):
        raise ValueError(f"face_uvs must have shape ({faces.shape[0]}, 3, 2), got {tuple(face_uvs.shape)}")
    if texture.dim() != 3 or texture.shape[0] != 3:
        raise ValueError(f"texture must have shape (3, Ht, Wt), got {tuple(texture.shape)}")
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
    material = trimesh.visual.material.SimpleMaterial(image=image, name=name)
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


def save_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike) -> list[Path]:
    """Write ``mesh`` to ``path``: ``.obj`` (with ``<stem>.mtl`` and ``<stem>.png`` beside it) or ``.glb``.

    Returns:
        the files written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".glb":
        path.write_bytes(mesh.export(file_type="glb"))
        return [path]
    if suffix != ".obj":
        raise ValueError(f"unsupported mesh format {path.suffix!r}: use .obj or .glb")
    # name the material after the file so that several exports can share a folder
    mesh = mesh.copy()
    mesh.visual.material.name = path.stem
    text, files = trimesh.exchange.obj.export_obj(mesh, return_texture=True, mtl_name=f"{path.stem}.mtl")
    path.write_text(text)
    written = [path]
    for fname, data in files.items():
        target = path.parent / fname
        target.write_bytes(data)
        written.append(target)
    return written
