"""Reference baselines: the template at the anchor pose, the fitted mean training shape, the fixed-shape wrapper."""

from __future__ import annotations

import inspect

import pytest
import torch

from tests.support.evaluation import IMAGE_SIZE, tiny_model
from unicorn.evaluation import (
    EvalOptions,
    EvaluableModel,
    FixedShapeModel,
    build_eval_dataset,
    evaluate,
    fit_silhouettes,
    mean_shape_baseline,
    template_baseline,
    training_point_clouds,
)
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.metrics import chamfer_l1, sample_points_from_meshes

FAST = dict(batch_size=3, num_points=400, icp_iterations=2, progress=False)


def _chamfer(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(chamfer_l1(a[None], b[None], factor=1.0)[0])


@pytest.mark.parametrize(("family", "elevation"), [("shapenet", 30.0), ("real", 10.0)])
def test_template_baseline_is_the_template_at_the_anchor_pose(family, elevation, shapenet_model, real_model) -> None:
    model = shapenet_model if family == "shapenet" else real_model
    baseline = template_baseline(model)
    images = torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE)
    with torch.no_grad():
        pred = baseline.predict(images)
        own = model.predict(images)
    # candidate 0: azimuth 0 (a full turn starts at 0), elevation at the centre of its range ((30, 30) for
    # ShapeNet, (-10, 30) otherwise), roll 0; the object 2.732 in front of the camera
    R = azim_elev_roll_to_rotation(torch.tensor(0.0), torch.tensor(elevation), torch.tensor(0.0))
    torch.testing.assert_close(pred.R, R.expand(2, 3, 3))
    torch.testing.assert_close(pred.T, torch.tensor([[0.0, 0.0, 2.732]] * 2))
    template = model.template.verts.expand(2, -1, -1)
    assert torch.equal(pred.verts, template) and torch.equal(pred.canonical_verts, template)
    assert torch.equal(pred.scale, torch.ones(2, 3))
    # every image selects candidate 0, whose pose is the one returned
    K = model.n_candidates
    assert pred.poses.probs.shape == (K, 2) and pred.poses.best.tolist() == [0, 0]
    assert torch.equal(pred.poses.probs.sum(0), torch.ones(2))
    torch.testing.assert_close(pred.poses.select()[0], pred.R)
    # texture and background are still the wrapped model's
    assert torch.equal(pred.texture, own.texture)
    assert (pred.background is None) == (own.background is None)


def test_fixed_shape_model_with_predicted_pose(shapenet_model) -> None:
    verts = shapenet_model.template.verts * 1.5
    fixed = FixedShapeModel(shapenet_model, verts, pose="predicted")
    images = torch.rand(3, 3, IMAGE_SIZE, IMAGE_SIZE)
    with torch.no_grad():
        pred, own = fixed.predict(images), shapenet_model.predict(images)
        rec, out = fixed(images)
    assert torch.equal(pred.R, own.R) and torch.equal(pred.T, own.T)
    assert torch.equal(pred.poses.probs, own.poses.probs)
    assert torch.equal(pred.verts, verts.expand(3, -1, -1)) and rec.shape == (3, 3, IMAGE_SIZE, IMAGE_SIZE)
    assert torch.equal(out.verts, pred.verts)
    # what evaluate() and the renders use, delegated to the wrapped (registered) model
    assert fixed.config is shapenet_model.config and fixed.template is shapenet_model.template
    assert fixed.renderer is shapenet_model.renderer and fixed.n_candidates == shapenet_model.n_candidates
    assert "fixed_verts" in fixed.state_dict() and fixed.eval() is fixed and not shapenet_model.training
    # .to() moves the fixed mesh with the wrapped model (a fresh model: the fixture is shared)
    fresh = FixedShapeModel(tiny_model("shapenet"), verts).to(torch.float64)
    assert fresh.fixed_verts.dtype == fresh.template.verts.dtype == torch.float64


def test_template_baseline_selects_one_candidate(shapenet_model, synth_root) -> None:
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=IMAGE_SIZE)
    result = evaluate(template_baseline(shapenet_model), data, EvalOptions("shapenet", **FAST), "synthetic")
    K = shapenet_model.n_candidates
    assert result.candidate_shares == {g: [1.0] + [0.0] * (K - 1) for g in ("chair", "mug")}
    assert all(row["candidate"] == 0 for row in result.per_image)
    for row in result.table:
        assert row["cand-share-min"] == 0.0 and row["cand-share-max"] == 1.0
    assert all(0 <= row["mask-iou"] <= 1 for row in result.per_image)


def _views(n: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """n cameras around the object, 20 degrees above it, 2.732 away (the ShapeNet family's distance)."""
    R = azim_elev_roll_to_rotation(torch.arange(n) * (360.0 / n), torch.full((n,), 20.0), torch.zeros(n))
    return R, torch.tensor([0.0, 0.0, 2.732]).expand(n, 3)


def test_fit_silhouettes_recovers_a_shape_from_its_masks(shapenet_model) -> None:
    model, faces = shapenet_model, shapenet_model.template.faces
    stretch = torch.tensor([1.3, 0.6, 0.9])
    target = model.template.verts * stretch  # a known shape on the template's topology
    R, T = _views()
    with torch.no_grad():
        _, alpha = model.render(target.expand(8, -1, -1), torch.full((8, 3, 4, 4), 0.5), R, T)
    masks = (alpha > 0.5).float()
    verts, iou = fit_silhouettes(model, masks, R, T, iterations=150)
    template, before = fit_silhouettes(model, masks, R, T, iterations=0)
    assert torch.equal(template, model.template.verts) and verts.shape == template.shape
    assert iou.shape == (8,) and before.mean() < 0.8 and iou.min() > 0.95
    # in 3D (independently of the renders): the extents of the target, and closer to it than the template
    extent = verts.amax(0) - verts.amin(0)
    truth = target.amax(0) - target.amin(0)
    # within two pixels at the object's distance (0.046 units at 32 px); the template's own extents are 0.06-0.24 off
    focal = float(model.renderer.rasterizer.camera.focal_length)
    pixel = 2 * float(T[0, 2]) / focal / masks.shape[-1]
    torch.testing.assert_close(extent, truth, atol=2 * pixel, rtol=0)

    def points(v: torch.Tensor) -> torch.Tensor:
        return sample_points_from_meshes(v, faces, 10_000, seed=3)[0]

    assert _chamfer(points(verts), points(target)) < 0.35 * _chamfer(points(template), points(target))
    with pytest.raises(ValueError, match=r"masks must have shape \(N, 1, 32, 32\)"):
        fit_silhouettes(model, masks[:, :, :16], R, T)
    with pytest.raises(ValueError, match=r"R must have shape \(\d+, 3, 3\)"):
        fit_silhouettes(model, masks, R[:7], T)
    with pytest.raises(ValueError, match="iterations >= 0"):
        fit_silhouettes(model, masks, R, T, iterations=-1)


def test_training_point_clouds_and_mean_shape_baseline(shapenet_model, synth_root) -> None:
    clouds = training_point_clouds(synth_root)
    assert len(clouds) == 2 and all(c.shape == (600, 3) for c in clouds)  # 2 categories x 1 train model
    train = build_eval_dataset("synthetic", str(synth_root), "train", img_size=IMAGE_SIZE)
    assert len(train) == 4  # 2 models x 2 views
    # one cloud per model, not per view, in the frame of the evaluation items' points (item k shows model k % 2)
    assert torch.equal(clouds[0], train[2]["points"]) and torch.equal(clouds[1], train[3]["points"])
    assert torch.equal(training_point_clouds(synth_root, "mug")[0], clouds[1])
    assert len(training_point_clouds(synth_root, max_models=1)) == 1
    assert training_point_clouds(synth_root, num_points=100)[0].shape == (100, 3)

    baseline = mean_shape_baseline(shapenet_model, clouds, iterations=100, num_points=300)
    assert isinstance(baseline, FixedShapeModel) and baseline.pose_mode == "predicted"
    options = EvalOptions("shapenet", oracle_pose=True, **FAST)
    mean = evaluate(baseline, train, options, "synthetic").mean
    template = evaluate(FixedShapeModel(shapenet_model, shapenet_model.template.verts), train, options).mean
    # on the shapes it was fitted to, at the ground-truth pose, the mean shape beats the template
    assert mean["chamfer-L1"] < template["chamfer-L1"] and mean["mask-iou"] > template["mask-iou"]


def test_bad_inputs(shapenet_model) -> None:
    V = shapenet_model.template.num_verts
    with pytest.raises(ValueError, match=rf"verts must have shape \({V}, 3\)"):
        FixedShapeModel(shapenet_model, torch.zeros(V + 1, 3))
    with pytest.raises(ValueError, match="pose must be one of"):
        FixedShapeModel(shapenet_model, shapenet_model.template.verts, pose="random")
    with pytest.raises(ValueError, match="finite"):
        FixedShapeModel(shapenet_model, torch.full((V, 3), float("nan")))
    with pytest.raises(TypeError, match="Unicorn"):
        FixedShapeModel(torch.nn.Linear(1, 1), torch.zeros(V, 3))  # type: ignore[arg-type]


def test_models_and_baselines_are_evaluable(shapenet_model) -> None:
    baseline = FixedShapeModel(shapenet_model, shapenet_model.template.verts.clone())
    for model in (shapenet_model, baseline):
        assert isinstance(model, EvaluableModel)
    assert not isinstance(torch.nn.Linear(2, 2), EvaluableModel)  # the check has teeth


def test_the_protocol_takes_the_arguments_evaluate_passes(shapenet_model) -> None:
    """A model written to the protocol's ``predict`` is called as ``evaluate`` calls it (``average_texture``)."""
    for predict in (EvaluableModel.predict, type(shapenet_model).predict, FixedShapeModel.predict):
        inspect.signature(predict).bind(shapenet_model, torch.zeros(1, 3, 8, 8), average_texture=True)
