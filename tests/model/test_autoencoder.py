"""The structured autoencoder: outputs, zero init, masks, switches, detaching, both training steps."""

from __future__ import annotations

import pytest
import torch

from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.model import Unicorn, merge_config

from .helpers import IMAGE_SIZE, ellipsoid_images, randomize_heads, tiny_config

# randomised heads can fold meshes into more layers than faces_per_pixel: irrelevant here
pytestmark = pytest.mark.filterwarnings("ignore:some pixels had more than faces_per_pixel")


def grads_of(module: torch.nn.Module) -> float:
    return sum(float(p.grad.abs().sum()) for p in module.parameters() if p.grad is not None)


def test_config_validation():
    with pytest.raises(KeyError, match="unknown key"):
        merge_config({"shape": {"code_size": 3}})
    with pytest.raises(KeyError, match="unknown model config group"):
        merge_config({"shapes": {}})
    with pytest.raises(FileNotFoundError, match="vgg16-397923af.pth"):
        Unicorn(tiny_config(loss={"perceptual": "vgg", "vgg_weights": "/nonexistent/vgg16.pth"}))


def test_prediction_shapes_and_ranges(tiny_model, images):
    randomize_heads(tiny_model)
    pred = tiny_model.predict(images)
    B, K = images.shape[0], tiny_model.n_candidates
    assert pred.verts.shape == (B, 642, 3) and pred.canonical_verts.shape == (B, 642, 3)
    assert pred.shape_code.shape == (B, 32) and pred.texture_code.shape == (B, 128)
    assert pred.background_code.shape == (B, 128)
    assert pred.texture.shape == (B, 3, 16, 16) and 0 <= pred.texture.min() and pred.texture.max() <= 1
    assert pred.background.shape == (B, 3, IMAGE_SIZE, IMAGE_SIZE)
    assert 0 <= pred.background.min() and pred.background.max() <= 1
    assert pred.scale.shape == (B, 3) and ((pred.scale >= 0.7) & (pred.scale <= 1.3)).all()
    assert pred.poses.R.shape == (K, B, 3, 3) and pred.poses.probs.shape == (K, B)
    assert torch.allclose(pred.poses.probs.sum(0), torch.ones(B))
    eye = torch.eye(3).expand(B, 3, 3)
    assert torch.allclose(pred.R @ pred.R.transpose(1, 2), eye, atol=1e-5)
    lo, hi = tiny_model.pose.R_init - tiny_model.pose.R_range, tiny_model.pose.R_init + tiny_model.pose.R_range
    assert ((pred.poses.angles >= lo[:, None] - 1e-4) & (pred.poses.angles <= hi[:, None] + 1e-4)).all()
    assert ((pred.T - torch.tensor([0, 0, 2.732])).abs() <= 0.3 + 1e-6).all()
    rec, _ = tiny_model(images)
    assert rec.shape == images.shape and torch.isfinite(rec).all()


def test_zero_init_gives_ellipsoid_identity_scale_anchor_poses(tiny_model, images):
    tiny_model.set_active_dims(shape=32, texture=128, background=128)
    pred = tiny_model.predict(images)
    template = tiny_model.template.verts
    assert torch.equal(pred.canonical_verts, template.expand_as(pred.canonical_verts))
    assert torch.equal(pred.scale, torch.ones_like(pred.scale))
    assert torch.equal(pred.verts, pred.canonical_verts)
    assert pred.shape_code.abs().sum() == 0 and pred.texture_code.abs().sum() == 0
    assert torch.allclose(pred.texture, torch.full_like(pred.texture, 0.5))  # zero code: grey
    init = tiny_model.pose.R_init
    anchors = azim_elev_roll_to_rotation(init[:, 0], init[:, 1], init[:, 2])
    assert torch.allclose(pred.poses.R, anchors[:, None].expand_as(pred.poses.R), atol=1e-6)
    assert torch.allclose(pred.T, torch.tensor([0.0, 0.0, 2.732]).expand_as(pred.T))
    assert torch.allclose(pred.R, anchors[pred.poses.best], atol=1e-6)


@pytest.mark.parametrize(("branch", "active"), [("shape", 2), ("texture", 8), ("background", 4)])
def test_masked_code_dims_change_nothing(tiny_model, images, branch, active):
    randomize_heads(tiny_model, std=0.1)
    tiny_model.set_active_dims(**{branch: active})
    head = getattr(tiny_model, branch)
    with torch.no_grad():
        before = tiny_model.predict(images)
        head.regressor[-1].weight[active:] += 1.0  # perturb only the masked code dims
        head.regressor[-1].bias[active:] -= 2.0
        after = tiny_model.predict(images)
        for name in ("verts", "texture", "background"):
            assert torch.equal(getattr(before, name), getattr(after, name)), name
        head.regressor[-1].bias[:active] += 0.5  # the active dims do matter
        changed = tiny_model.predict(images)
    key = {"shape": "verts", "texture": "texture", "background": "background"}[branch]
    assert not torch.allclose(getattr(before, key), getattr(changed, key))
    state = tiny_model.state_dict()
    assert int(state[f"{branch}.mask.active"]) == active


def test_stage_switches_and_texture_averaging(tiny_model, images):
    randomize_heads(tiny_model, std=0.1)
    tiny_model.set_active_dims(shape=4)
    tiny_model.set_stage_switches(translation=False, deformation=False, scale=False)
    pred = tiny_model.predict(images)
    assert torch.allclose(pred.T, torch.tensor([0.0, 0.0, 2.732]).expand_as(pred.T))
    assert torch.equal(pred.verts, tiny_model.template.verts.expand_as(pred.verts))
    assert torch.equal(pred.scale, torch.ones_like(pred.scale))
    tiny_model.set_stage_switches(translation=True, deformation=True, scale=True)
    pred = tiny_model.predict(images, average_texture=True)
    assert not torch.equal(pred.verts, tiny_model.template.verts.expand_as(pred.verts))
    flat = pred.texture.flatten(2)
    assert torch.allclose(flat, flat[..., :1].expand_as(flat))
    assert torch.allclose(flat[..., 0], tiny_model.predict(images).texture.mean((2, 3)), atol=1e-6)


@pytest.mark.parametrize("size", ["small", "big"])
def test_pose_step_gradients_only_reach_the_pose_branch(size, images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(size=size))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    losses = model.pose_step(images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "total"}
    losses["total"].backward()
    for head in (*model.pose.rot_regressors, *model.pose.T_regressors, model.pose.proba_regressor):
        assert grads_of(head) > 0
    for module in (model.shape, model.texture, model.background, model.scale):
        assert grads_of(module) == 0
    if size == "small":
        assert grads_of(model.encoders[0]) > 0
    else:
        assert grads_of(model.encoders[2]) > 0
        assert all(grads_of(model.encoders[i]) == 0 for i in (0, 1, 3))


def test_pose_step_assigned_objective(images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"pose_objective": "assigned", "assignment_weight": 0.5}))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    losses = model.pose_step(images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "assignment", "total"}
    # the value: cross-entropy against the candidate with the lowest reconstruction loss, computed here from
    # the model's own predictions rendered candidate by candidate
    with torch.no_grad():
        pred = model.predict(images)
        per_candidate = []
        for k in range(model.n_candidates):
            rec, _ = model.render(pred.verts, pred.texture, pred.poses.R[k], pred.poses.T[k], pred.background)
            per_candidate.append(sum(model.reconstruction_terms(rec, images).values()))
        best = torch.stack(per_candidate).argmin(0)
        expected = torch.nn.functional.cross_entropy(pred.poses.probs.log().T, best)
    assert torch.allclose(losses["assignment"], 0.5 * expected, rtol=1e-4)
    # the reconstruction terms train the poses but not the probabilities; the cross-entropy trains these
    losses["rgb"].backward(retain_graph=True)
    assert grads_of(model.pose.proba_regressor) == 0
    assert grads_of(model.pose.rot_regressors[0]) > 0
    losses["assignment"].backward()
    assert grads_of(model.pose.proba_regressor) > 0
    with pytest.raises(ValueError, match="pose_objective"):
        Unicorn(tiny_config(loss={"pose_objective": "best"}))


@pytest.mark.parametrize("size", ["small", "big"])
def test_step_3d_gradients_skip_the_pose_branch(size, images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(size=size))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    losses = model.step_3d(images)
    assert {"rgb", "perceptual", "normal", "laplacian", "total"} <= set(losses)
    assert torch.allclose(losses["total"], sum(v for k, v in losses.items() if k != "total"))
    losses["total"].backward()
    assert grads_of(model.pose) == 0
    for module in (model.shape.field, model.shape.regressor, model.texture, model.background, model.scale):
        assert grads_of(module) > 0
    if size == "big":
        assert grads_of(model.encoders[2]) == 0
        assert all(grads_of(model.encoders[i]) > 0 for i in (0, 1, 3))


def test_neighbor_term_gradients_reach_only_shape_and_texture(images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config())
    randomize_heads(model, std=0.1)
    model.set_active_dims(shape=2, texture=8)
    assert "neighbor" not in Unicorn(tiny_config()).step_3d(images)  # shape code 0-dim: inactive
    # memory with other viewpoints so that every sample has neighbours
    with torch.no_grad():
        other = torch.rand(6, 3, IMAGE_SIZE, IMAGE_SIZE)
        pred = model.predict(other)
        turn = azim_elev_roll_to_rotation(torch.linspace(40, 160, 6), torch.zeros(6))
        model.memory.push(other, pred.shape_code, pred.texture_code, turn)
    losses = model.step_3d(images)
    assert "neighbor" in losses and losses["neighbor"].item() > 0
    losses["neighbor"].backward()  # the neighbour term alone
    assert grads_of(model.shape.field) > 0 and grads_of(model.texture.generator) > 0
    assert grads_of(model.background) == 0 and grads_of(model.scale) == 0 and grads_of(model.pose) == 0
    assert len(model.memory) == 6 + images.shape[0]


def test_shapenet_model_without_background():
    torch.manual_seed(0)
    model = Unicorn(tiny_config("shapenet", "big"))
    assert model.background is None and len(model.encoders) == 3
    assert model.shape.field.linear_x.out_features == 512
    assert model.config["renderer"]["focal_length"] > 3.7
    x = ellipsoid_images(2)
    pose, step = model.pose_step(x), model.step_3d(x)
    assert all(torch.isfinite(v) for v in [*pose.values(), *step.values()])


def test_both_steps_decrease_losses_on_synthetic_renders():
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"memory_size": 32}))
    model.set_active_dims(shape=2, texture=8)
    data = ellipsoid_images(8)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    history: dict[str, list[float]] = {"pose": [], "3d": []}
    g = torch.Generator().manual_seed(0)
    for it in range(24):
        batch = data[torch.randperm(8, generator=g)[:4]]
        optimizer.zero_grad(set_to_none=True)
        losses = model.pose_step(batch) if it % 2 == 0 else model.step_3d(batch)
        assert all(torch.isfinite(v) for v in losses.values()), losses
        losses["total"].backward()
        optimizer.step()
        history["pose" if it % 2 == 0 else "3d"].append(losses["total"].item())
    for name, values in history.items():
        first, last = sum(values[:4]) / 4, sum(values[-4:]) / 4
        assert last < 0.7 * first, (name, values)


def test_neighbour_parameters_equal_the_matching_parts_of_predict(tiny_model, images):
    """The neighbour swaps compute only what they use; each part equals what predict() gives."""
    randomize_heads(tiny_model)
    tiny_model.set_active_dims(shape=4, texture=4, background=4)
    batch = torch.cat([images, images.flip(0)])  # 2n images: n shape then n texture neighbours
    n = images.shape[0]
    with torch.no_grad():
        full = tiny_model.predict(batch)
        scale, maps, verts, R, T, bkg = tiny_model._neighbour_parameters(batch, n, average_texture=False)
    torch.testing.assert_close(scale, full.scale[:n])
    torch.testing.assert_close(maps, full.texture[:n])
    torch.testing.assert_close(verts, full.verts[n:])
    torch.testing.assert_close(R, full.R)
    torch.testing.assert_close(T, full.T)
    torch.testing.assert_close(bkg, full.background)
