"""ShapeNet-NMR loader (DVR form) on the synthetic benchmark and on hand-written DVR cameras."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from unicorn.data.images import DatasetNotFoundError
from unicorn.data.shapenet import (
    ShapeNetNMR,
    dvr_to_unicorn_points,
    dvr_to_unicorn_pose,
    unicorn_to_dvr_points,
    unicorn_to_dvr_world_mat,
)
from unicorn.data.synthetic.sampling import views_to_cameras
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.geometry.rotations import look_at_view_transform

A_ROW = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
FLIP = np.diag([-1.0, -1.0, 1.0])


def test_pose_conversion_matches_reference_formula() -> None:
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R_dvr = q * np.sign(np.linalg.det(q))
    t = rng.normal(size=3)
    world_mat = np.eye(4)
    world_mat[:3, :3], world_mat[:3, 3] = R_dvr, t
    R, T = dvr_to_unicorn_pose(world_mat)
    assert np.allclose(R, A_ROW @ R_dvr.T @ FLIP)  # the reference's rotation
    assert np.allclose(T, t * [-1, -1, 1])  # translation flipped too (the reference copies it)
    assert np.allclose(unicorn_to_dvr_world_mat(R, T), world_mat)
    pts = rng.normal(size=(5, 3))
    assert np.allclose(dvr_to_unicorn_points(pts), pts @ A_ROW.T)
    assert np.allclose(unicorn_to_dvr_points(dvr_to_unicorn_points(pts)), pts)


def test_conversion_is_consistent_with_projection() -> None:
    """A DVR camera and its converted unicorn pose see the same point at mirrored OpenCV/NDC coordinates."""
    R, T = look_at_view_transform(2.732, 30.0, 45.0)
    R, T = R[0].double().numpy(), T[0].double().numpy() + [0.1, -0.05, 0.0]
    world_mat = unicorn_to_dvr_world_mat(R, T)
    p_uni = np.array([0.2, -0.1, 0.3])
    p_cv = world_mat[:3, :3] @ unicorn_to_dvr_points(p_uni) + world_mat[:3, 3]
    p_view = p_uni @ R + T
    assert np.allclose(p_view, p_cv * [-1, -1, 1])


def test_items_shapes_and_ranges(synth_nmr: Path) -> None:
    ds = ShapeNetNMR(synth_nmr, split="test", views="random", with_points=True)
    assert len(ds) == 2  # one test model per category, one view each
    ds = ShapeNetNMR(synth_nmr, categories=["chair", "car"], split="train", with_points=True, n_points=256)
    assert ds.n_views == 6 and len(ds) == 2 * 1 * 6  # 3 models: 1 train, 1 val, 1 test
    for i in (0, len(ds) - 1):
        item = ds[i]
        assert item["image"].shape == (3, 64, 64) and item["image"].dtype == torch.float32
        assert item["mask"].shape == (1, 64, 64) and set(item["mask"].unique().tolist()) <= {0.0, 1.0}
        assert 0 <= item["image"].min() and item["image"].max() <= 1
        assert item["R"].shape == (3, 3) and item["T"].shape == (3,) and item["has_pose"]
        assert item["points"].shape == (256, 3) and item["normals"].shape == (256, 3)
        assert abs(item["points"].abs().max().item() - 0.5) < 0.01  # ShapeNet normalisation
        assert torch.allclose(item["normals"].norm(dim=1), torch.ones(256), atol=2e-3)
        assert torch.allclose(item["R"] @ item["R"].T, torch.eye(3), atol=1e-5)
    # train items carry no points by default
    assert "points" not in ShapeNetNMR(synth_nmr, split="train")[0]


@pytest.mark.parametrize("fixture", ["synth_nmr", "synth_wild"])
def test_pose_round_trip(fixture: str, request: pytest.FixtureRequest) -> None:
    root = request.getfixturevalue(fixture)
    ds = ShapeNetNMR(root, split="train")
    for i in range(len(ds)):
        item = ds[i]
        with np.load(ds.model_dir(i) / "views.npz") as views:
            R, T = views_to_cameras({k: views[k].astype(np.float64) for k in views.files})
        v = int(item["view"])
        assert np.allclose(item["R"].numpy(), R[v], atol=1e-5)
        assert np.allclose(item["T"].numpy(), T[v], atol=1e-5)


@pytest.mark.parametrize("fixture", ["synth_nmr", "synth_wild"])
def test_projected_points_land_in_masks(fixture: str, request: pytest.FixtureRequest) -> None:
    root = request.getfixturevalue(fixture)
    ds = ShapeNetNMR(root, split="train", with_points=True)
    camera = PerspectiveCamera(fov=30.0)
    for i in range(0, len(ds), 3):
        item = ds[i]
        screen = camera.transform_points_screen(item["points"][None], item["R"][None], item["T"][None], 64)[0]
        col, row = screen[:, 0].round().long(), screen[:, 1].round().long()
        inside = (col >= 0) & (col < 64) & (row >= 0) & (row < 64)
        # masks are thresholded at half coverage, so sub-pixel parts may vanish: allow a 1-pixel margin
        dilated = F.max_pool2d(item["mask"][None], 3, 1, 1)[0, 0]
        hits = dilated[row[inside], col[inside]]
        assert hits.mean() == 1.0, f"item {i}: {1 - hits.mean():.3f} of the points project outside the mask"
        assert item["mask"][0][row[inside], col[inside]].mean() > 0.75


def test_random_views_are_seeded(synth_nmr: Path) -> None:
    a = ShapeNetNMR(synth_nmr, split="train", views="random", seed=3)
    b = ShapeNetNMR(synth_nmr, split="train", views="random", seed=3)
    assert len(a) == 2 and [int(a[i]["view"]) for i in range(2)] == [int(b[i]["view"]) for i in range(2)]


def test_include_test_adds_models(synth_nmr: Path) -> None:
    assert len(ShapeNetNMR(synth_nmr, "chair", split="train", include_test=True)) == 3 * 6


def test_categories_by_name_or_synset(synth_nmr: Path) -> None:
    assert ShapeNetNMR(synth_nmr, "synthetic_car").synsets == ["90000003"]
    assert ShapeNetNMR(synth_nmr, ["90000001"]).synsets == ["90000001"]
    with pytest.raises(ValueError, match="unknown ShapeNet category 'sofa'"):
        ShapeNetNMR(synth_nmr, "sofa")


def test_missing_root_and_files(tmp_path: Path, synth_nmr: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match=r"nowhere.*NMR_Dataset\.zip"):
        ShapeNetNMR(tmp_path / "nowhere")
    broken = tmp_path / "broken"
    shutil.copytree(synth_nmr, broken)
    (broken / "90000001" / "softras_val.lst").unlink()
    with pytest.raises(DatasetNotFoundError, match="softras_val.lst"):
        ShapeNetNMR(broken, "chair", split="val")
    (broken / "metadata.yaml").unlink()
    with pytest.raises(DatasetNotFoundError, match="metadata.yaml"):
        ShapeNetNMR(broken)
