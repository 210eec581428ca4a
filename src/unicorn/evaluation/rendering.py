"""Hard renders of predicted meshes: masks, face visibility, pictures from several viewpoints and turntables.

Everything here uses the ``"hard"`` renderer (nearest face per pixel, supersampled), UNICORN's renderer for
evaluation masks and visualisations, with the model's own camera so that a mesh drawn with its predicted pose
lands where the model put it. Turntables spin the object about its vertical (object +Y) axis in front of the
predicted camera (so the first frame is the input viewpoint), centred and far enough to be seen whole.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from unicorn.evaluation.interface import EvaluableModel
from unicorn.render import BACKGROUND_COLOR, RenderOutput, TexturesVertex, build_renderer

__all__ = [
    "SHADE_COLOR",
    "even_angles",
    "fit_pose",
    "hard_render",
    "shaded_render",
    "spin_rotation",
    "turntable",
    "vertex_normals",
    "vertex_visibility",
]

#: base colour of the shaded (untextured) geometry renders
SHADE_COLOR = (0.72, 0.76, 0.85)


def _hard(model: EvaluableModel, image_size: int, supersample: int, device: torch.device) -> torch.nn.Module:
    return build_renderer(
        "hard",
        image_size=image_size,
        supersample=supersample,
        camera=model.renderer.camera,
        background_color=BACKGROUND_COLOR,
    ).to(device)


def hard_render(
    model: EvaluableModel,
    verts: torch.Tensor,
    maps: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    image_size: int,
    supersample: int = 2,
    background: torch.Tensor | None = None,
) -> RenderOutput:
    """Textured hard render of the model's meshes.

    Args:
        model: the model (template faces and UVs, camera).
        verts: (B, V, 3) object-frame vertices.
        maps: (B, 3, Ht, Wt) UV textures.
        R: (B, 3, 3) world-to-view rotations; T: (B, 3) translations.
        image_size: output side.
        supersample: rasterisation at ``supersample * image_size``, averaged (anti-aliased edges).
        background: (B, 3, image_size, image_size) images behind the mesh, white when None.

    Returns:
        :class:`~unicorn.render.RenderOutput`: ``images`` (B, 4, S, S) (RGB then alpha) and ``face_ids``
        (B, sS, sS) at the supersampled resolution.
    """
    renderer = _hard(model, image_size, supersample, verts.device)
    return renderer.render(verts, model.template.faces, model.textures(maps), R=R, T=T, background=background)


def vertex_visibility(face_ids: torch.Tensor, faces: torch.Tensor, num_verts: int) -> torch.Tensor:
    """Vertices of the faces hit by a hard rasterisation (UNICORN's visibility for keypoint transfer).

    Args:
        face_ids: (B, H, W) long face index per pixel, -1 for background (``RenderOutput.face_ids``; batch-local
            indices in [0, F)).
        faces: (F, 3) long.
        num_verts: V.

    Returns:
        (B, V) bool.
    """
    B = face_ids.shape[0]
    F = faces.shape[0]
    hit = torch.zeros(B, F + 1, dtype=torch.bool, device=face_ids.device)
    ids = face_ids.reshape(B, -1).long()
    hit.scatter_(1, torch.where(ids < 0, F, ids), True)  # background pixels land in the spare column F
    hit = hit[:, :F]
    visible = torch.zeros(B, num_verts, dtype=torch.bool, device=face_ids.device)
    for corner in range(3):
        idx = faces[:, corner].to(face_ids.device).expand(B, -1)
        visible.scatter_reduce_(1, idx, hit, reduce="amax")
    return visible


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (B, V, 3) of meshes (B, V, 3) with faces (F, 3)."""
    f = faces.long().to(verts.device)
    v0, v1, v2 = verts[:, f[:, 0]], verts[:, f[:, 1]], verts[:, f[:, 2]]
    face_n = torch.cross(v1 - v0, v2 - v0, dim=-1)  # (B, F, 3), length = 2 * area
    normals = torch.zeros_like(verts)
    for corner in range(3):
        normals.index_add_(1, f[:, corner], face_n)
    return torch.nn.functional.normalize(normals, dim=-1, eps=1e-12)


def shaded_render(
    model: EvaluableModel,
    verts: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    image_size: int,
    supersample: int = 2,
    color: Sequence[float] = SHADE_COLOR,
) -> torch.Tensor:
    """Untextured geometry lit by a light at the camera (two-sided Lambert plus ambient), on white.

    Args:
        model: the model (faces, camera).
        verts: (B, V, 3) object-frame vertices; R: (B, 3, 3); T: (B, 3).
        image_size: output side.
        supersample: anti-aliasing factor.
        color: RGB base colour.

    Returns:
        (B, 4, S, S) images, RGB then alpha.
    """
    faces = model.template.faces
    normals = vertex_normals(verts, faces) @ R  # view frame (+Z away from the camera)
    light = verts.new_tensor([0.35, 0.45, -1.0])  # from the camera, slightly above and to the left
    light = light / light.norm()
    lambert = (normals @ light).abs().unsqueeze(-1)  # two-sided: open surfaces are lit from both sides
    colors = verts.new_tensor(list(color)) * (0.3 + 0.7 * lambert)
    renderer = _hard(model, image_size, supersample, verts.device)
    return renderer(verts, faces, TexturesVertex(colors.clamp(0, 1)), R=R, T=T)


def spin_rotation(angles: torch.Tensor) -> torch.Tensor:
    """Rotations (N, 3, 3) about the object's +Y axis by ``angles`` (N,) degrees, applied as ``x @ M``."""
    a = torch.deg2rad(angles)
    c, s = a.cos(), a.sin()
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    return torch.stack(
        [torch.stack([c, zero, -s], -1), torch.stack([zero, one, zero], -1), torch.stack([s, zero, c], -1)], -2
    )


def fit_pose(
    verts: torch.Tensor, R: torch.Tensor, T: torch.Tensor, focal_length: float, margin: float = 1.1
) -> tuple[torch.Tensor, torch.Tensor]:
    """The spin centre and a translation that keep a mesh whole and centred in view whatever its spin.

    The mesh's bounding-box centre ``c`` goes on the optical axis at the predicted depth, pushed back if needed so
    that its bounding sphere (radius ``r`` about ``c``, unchanged by any rotation about ``c``) fits the view with
    ``margin``.

    Args:
        verts: (V, 3) object-frame vertices; R: (3, 3); T: (3,) the predicted pose.
        focal_length: the camera's focal length in NDC units.
        margin: how much smaller than the view the sphere's nearest cross-section must be.

    Returns:
        centre (3,) and T_fit (3,), so that ``((v - c) @ M + c) @ R + T_fit`` views a mesh spun by ``M``.
    """
    centre = 0.5 * (verts.amin(0) + verts.amax(0))
    radius = (verts - centre).norm(dim=-1).max()
    depth = (centre @ R + T)[2]
    depth = torch.maximum(depth, radius * (1 + margin * focal_length))
    return centre, torch.stack([depth.new_zeros(()), depth.new_zeros(()), depth]) - centre @ R


def turntable(
    model: EvaluableModel,
    verts: torch.Tensor,
    maps: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    angles: Sequence[float] | int = 24,
    image_size: int = 128,
    shaded: bool = False,
    fit: bool = True,
    supersample: int = 2,
    chunk: int = 16,
) -> torch.Tensor:
    """Views of one mesh spinning about its vertical axis in front of its predicted camera.

    Args:
        model: the model.
        verts: (V, 3) object-frame vertices; maps: (3, Ht, Wt) texture; R: (3, 3); T: (3,) predicted pose.
        angles: spin angles in degrees, or a number of evenly spaced frames over a full turn (first at 0).
        image_size: side of the frames.
        shaded: untextured lit geometry instead of the texture.
        fit: spin about the mesh's bounding-box centre, centred in view and far enough to be seen whole
            (:func:`fit_pose`); False spins about the object origin with the predicted pose, so that angle 0 is
            exactly the predicted view.
        supersample: anti-aliasing factor.
        chunk: frames rendered at once.

    Returns:
        (N, 4, S, S) frames on white, RGB then alpha.
    """
    if isinstance(angles, int):
        angles = [360.0 * k / angles for k in range(angles)]
    spins = spin_rotation(torch.tensor([float(a) for a in angles], device=verts.device, dtype=verts.dtype))
    centre = verts.new_zeros(3)
    if fit:
        centre, T = fit_pose(verts, R, T, float(model.renderer.camera.focal_length))
    frames = []
    for start in range(0, spins.shape[0], chunk):
        m = spins[start : start + chunk]
        n = m.shape[0]
        v = (verts - centre).unsqueeze(0) @ m + centre  # (n, V, 3)
        Rn, Tn = R.expand(n, 3, 3), T.expand(n, 3)
        if shaded:
            frames.append(shaded_render(model, v, Rn, Tn, image_size, supersample))
        else:
            frames.append(hard_render(model, v, maps.expand(n, -1, -1, -1), Rn, Tn, image_size, supersample).images)
    return torch.cat(frames)


def even_angles(n: int, offset: float = 0.0) -> list[float]:
    """``n`` evenly spaced angles over a full turn starting at ``offset`` degrees."""
    return [math.fmod(offset + 360.0 * k / n, 360.0) for k in range(n)]
