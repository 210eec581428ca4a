"""Hard renders for masks, visibility, mesh views and turntables."""

from __future__ import annotations

import torch

from tests.support.evaluation import IMAGE_SIZE
from unicorn.evaluation import hard_render, shaded_render, turntable, vertex_visibility
from unicorn.evaluation.rendering import spin_rotation, vertex_normals
from unicorn.geometry.mesh import icosphere


def test_vertex_visibility() -> None:
    faces = torch.tensor([[0, 1, 2], [2, 3, 4], [4, 5, 0]])
    face_ids = torch.tensor([[[-1, 0], [0, -1]], [[2, 2], [-1, 1]]])  # (2, 2, 2)
    visible = vertex_visibility(face_ids, faces, 7)
    assert visible.tolist() == [
        [True, True, True, False, False, False, False],
        [True, False, True, True, True, True, False],
    ]


def test_spin_and_normals() -> None:
    M = spin_rotation(torch.tensor([0.0, 90.0, 200.0]))
    torch.testing.assert_close(M[0], torch.eye(3))
    torch.testing.assert_close(M @ M.transpose(1, 2), torch.eye(3).expand(3, 3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(
        torch.tensor([[1.0, 5.0, 0.0]]) @ M[1], torch.tensor([[0.0, 5.0, -1.0]]), atol=1e-6, rtol=0
    )
    verts, faces = icosphere(2)
    normals = vertex_normals(verts[None], faces)[0]
    assert torch.nn.functional.cosine_similarity(normals, verts, dim=-1).min() > 0.99  # a sphere's normals are radial


def test_turntable_starts_at_the_predicted_view(real_model) -> None:
    x = torch.rand(1, 3, IMAGE_SIZE, IMAGE_SIZE)
    with torch.no_grad():
        pred = real_model.predict(x)
        out = hard_render(real_model, pred.verts, pred.texture, pred.R, pred.T, 24)
        frames = turntable(real_model, pred.verts[0], pred.texture[0], pred.R[0], pred.T[0], 4, 24, fit=False)
        fitted = turntable(real_model, pred.verts[0] * 3 + 0.4, pred.texture[0], pred.R[0], pred.T[0], 6, 24)
        shaded = shaded_render(real_model, pred.verts, pred.R, pred.T, 24)
    assert out.images.shape == (1, 4, 24, 24) and out.face_ids.shape == (1, 48, 48)  # 2x supersampled ids
    assert frames.shape == (4, 4, 24, 24)
    torch.testing.assert_close(frames[0], out.images[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(shaded[:, 3:], out.images[:, 3:])  # same silhouette, other colours
    assert 0 < float(out.images[0, 3].mean()) < 1
    # a big off-centre mesh is framed whole: nothing touches the border, the silhouette is centred
    alpha = fitted[:, 3]
    assert float(alpha[:, 0].max() + alpha[:, -1].max() + alpha[:, :, 0].max() + alpha[:, :, -1].max()) == 0
    cols = (alpha.sum(1) * torch.arange(24.0)).sum(1) / alpha.sum((1, 2))
    assert ((cols - 11.5).abs() < 2.5).all()


def test_default_mask_supersampling_gives_unbiased_silhouettes() -> None:
    """The oracle: each pixel's coverage from 9 x 9 samples, the silhouette its pixels more than half covered.
    EvalOptions' odd default agrees with it on area and IoU; 2 x 2 samples (a half-covered pixel averages exactly
    0.5 and drops out of ``> 0.5``) shrink every silhouette."""
    from unicorn.evaluation import EvalOptions
    from unicorn.geometry.cameras import PerspectiveCamera
    from unicorn.geometry.rotations import look_at_view_transform
    from unicorn.metrics import mask_iou
    from unicorn.render import TexturesVertex, build_renderer

    g = torch.Generator().manual_seed(0)
    v, faces = icosphere(2)
    B = 16
    verts = v[None] * (0.3 + 0.5 * torch.rand(B, 1, 3, generator=g))
    elev, azim = 40 * torch.rand(B, generator=g) - 20, 360 * torch.rand(B, generator=g)
    R, T = look_at_view_transform(dist=2.7, elev=elev, azim=azim)
    textures = TexturesVertex(torch.ones(B, v.shape[0], 3))

    def coverage(supersample: int) -> torch.Tensor:
        renderer = build_renderer("hard", image_size=32, supersample=supersample, camera=PerspectiveCamera(fov=30.0))
        return renderer(verts, faces, textures, R=R, T=T)[:, 3]

    reference = (coverage(9) > 0.5).float()

    def area_ratio(alpha: torch.Tensor) -> float:
        return ((alpha > 0.5).float().sum((1, 2)) / reference.sum((1, 2))).mean().item()

    default = coverage(EvalOptions().mask_supersample)
    assert abs(area_ratio(default) - 1.0) < 0.005 and mask_iou(default, reference).item() > 0.995
    assert area_ratio(coverage(2)) < 0.98
