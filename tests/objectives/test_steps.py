"""The training objectives: what each step's gradients reach, its terms, and the pose probabilities it returns."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import IMAGE_SIZE, ellipsoid_images, randomize_heads, tiny_config
from unicorn.data.augment import random_roll_shift
from unicorn.geometry.rotations import azim_elev_roll_to_rotation, rotation_angle_between
from unicorn.model import Unicorn
from unicorn.objectives import (
    AssignedLoss,
    Objectives,
    StepLosses,
    candidate_spacing_loss,
    flip_consistency_loss,
    view_equivariance_loss,
)

# randomised heads can fold meshes into more layers than faces_per_pixel: irrelevant here
pytestmark = pytest.mark.filterwarnings("ignore:some pixels had more than faces_per_pixel")


def objectives_of(model: Unicorn) -> Objectives:
    return Objectives.from_config(model.config["loss"], model)


def grads_of(module: torch.nn.Module) -> float:
    return sum(float(p.grad.abs().sum()) for p in module.parameters() if p.grad is not None)


#: encoder layouts: the paper's small (one shared) and big (one per branch) models, and a shared encoder with one
#: branch reading its own (``encoder.own``)
LAYOUTS = {
    "small": {},
    "big": {"size": "big"},
    "own background": {"encoder": {"own": ["background"]}},
    "own pose": {"encoder": {"own": ["pose"]}},
}


def encoders_read_by(model: Unicorn, branches) -> set[int]:
    return {model.encoder_index[b] for b in branches}


def vivid_textures(model: Unicorn, gain: float = 30.0) -> None:
    """Scale the texture generator's RGB outputs: saturated textures unlike the grey backgrounds."""
    with torch.no_grad():
        for conv in model.texture.generator.conv_rgb:
            conv.weight.mul_(gain)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_both_steps_return_the_batch_pose_probabilities(layout, images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(**LAYOUTS[layout])).eval()  # eval: batch norm is the same in every call
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    with torch.no_grad():
        expected = model.predict(images).poses.probs  # (K, B)
    objectives = objectives_of(model)
    for step in (objectives.pose_step, objectives.step_3d):
        losses = step(model, images)
        assert isinstance(losses, StepLosses)
        assert losses.probs.shape == (model.n_candidates, images.shape[0]) and not losses.probs.requires_grad
        assert torch.allclose(losses.probs, expected, atol=1e-6)
        assert torch.allclose(losses["total"], sum(v for k, v in losses.items() if k != "total"))


@pytest.mark.parametrize("layout", ["small", "own pose"])  # the pose features shared with the 3D branches or not
def test_step_3d_renders_the_most_likely_candidate(layout, images):
    """The 3D step's reconstruction terms against the model's prediction rendered here at each image's most likely
    candidate (indexed by hand): not candidate 0, whose render reconstructs differently."""
    torch.manual_seed(0)
    model = Unicorn(tiny_config(**LAYOUTS[layout])).eval()  # eval: batch norm is the same in every call
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    vivid_textures(model)  # else the object is as grey as the background: the candidates' renders hardly differ
    objectives = objectives_of(model)
    reconstruction = objectives.steps["3d"].reconstruction
    b = torch.arange(images.shape[0])
    with torch.no_grad():
        pred = model.predict(images)
        best = pred.poses.probs.argmax(0)  # (B,)
        assert (best != 0).all()  # else rendering candidate 0 would pass too

        def terms_at(k: torch.Tensor) -> dict[str, torch.Tensor]:
            R, T = pred.poses.R[k, b], pred.poses.T[k, b]
            rec, _ = model.render(pred.verts, pred.texture, R, T, pred.background)
            return reconstruction(rec, images)

        expected, first = terms_at(best), terms_at(torch.zeros_like(best))
    losses = objectives.step_3d(model, images)
    for name in ("rgb", "perceptual"):
        assert not torch.allclose(first[name], expected[name], rtol=1e-3)
        assert torch.allclose(losses[name], expected[name].mean(), rtol=1e-4)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_pose_step_gradients_only_reach_the_pose_branch(layout, images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(**LAYOUTS[layout]))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    losses = objectives_of(model).pose_step(model, images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "total"}
    losses["total"].backward()
    for head in (*model.pose.rot_regressors, *model.pose.T_regressors, model.pose.proba_regressor):
        assert grads_of(head) > 0
    for module in (model.shape, model.texture, model.background, model.scale):
        assert grads_of(module) == 0
    pose_encoder = model.encoder_index["pose"]
    assert len(model.encoders) == {"small": 1, "big": 4}.get(layout, 2)
    for i, encoder in enumerate(model.encoders):
        assert (grads_of(encoder) > 0) == (i == pose_encoder)


def test_pose_step_assigned_objective(images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"pose_objective": "assigned", "assignment_weight": 0.5}))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    objectives = objectives_of(model)
    assert isinstance(objectives.steps["pose"].objective, AssignedLoss)
    losses = objectives.pose_step(model, images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "assignment", "total"}
    # the value: cross-entropy against the candidate with the lowest reconstruction loss, computed here from
    # the model's own predictions rendered candidate by candidate
    with torch.no_grad():
        pred = model.predict(images)
        per_candidate = []
        for k in range(model.n_candidates):
            rec, _ = model.render(pred.verts, pred.texture, pred.poses.R[k], pred.poses.T[k], pred.background)
            per_candidate.append(sum(objectives.steps["pose"].reconstruction(rec, images).values()))
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
        Objectives.from_config({**model.config["loss"], "pose_objective": "best"}, model)


def test_pose_step_spacing_term_moves_the_candidates_only(images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"spacing_weight": 0.5, "spacing_angle": 90.0}))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    losses = objectives_of(model).pose_step(model, images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "spacing", "total"}
    with torch.no_grad():
        expected = 0.5 * candidate_spacing_loss(model.predict(images).poses.R, 90.0)
    assert float(expected) > 0 and torch.allclose(losses["spacing"], expected, rtol=1e-5)
    assert torch.allclose(losses["total"], sum(v for k, v in losses.items() if k != "total"))
    losses["spacing"].backward()
    assert grads_of(model.pose.proba_regressor) == 0
    assert all(grads_of(head) > 0 for head in model.pose.rot_regressors)
    assert all(grads_of(head) == 0 for head in model.pose.T_regressors)
    # left out at weight 0 (the default, the paper's)
    assert "spacing" not in objectives_of(Unicorn(tiny_config())).pose_step(model, images)


def test_sampled_schedule_renders_the_picked_candidate_in_both_steps(images):
    torch.manual_seed(0)
    loss = {"pose_objective": "sampled", "uniform_weight": 0.0, "score_weight": 0.5, "sample_uniform_until": 0}
    model = Unicorn(tiny_config(loss=loss)).eval()  # eval: batch norm is the same in every call
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    objectives = objectives_of(model)
    sampled = objectives.steps["pose"].objective
    assert objectives.steps["3d"].objective is sampled
    reconstruction = objectives.steps["pose"].reconstruction
    B = images.shape[0]
    with torch.no_grad():
        pred = model.predict(images)
    logits = pred.poses.logits
    for kind in ("pose", "3d"):
        # the same draws as the step's: the pick uses torch's global generator
        torch.manual_seed(7)
        picked = sampled.pick(logits, 300)
        torch.manual_seed(7)
        losses = objectives(kind, model, images, iteration=300)
        with torch.no_grad():
            R, T = pred.poses.select(picked)
            rec, _ = model.render(pred.verts, pred.texture, R, T, pred.background)
            terms = reconstruction(rec, images)
            w = sampled.weights(logits, picked, 300)
        for name in ("rgb", "perceptual"):
            assert torch.allclose(losses[name], (w * terms[name]).mean(), rtol=1e-4)
        if kind == "pose":
            target = sum(terms.values())
            score = 0.5 * (-logits[picked, torch.arange(B)] - target).square().mean()
            assert torch.allclose(losses["score"], score, rtol=1e-4)
            losses["total"].backward()
            assert grads_of(model.pose.proba_regressor) > 0
            assert grads_of(model.texture) == 0
        else:
            assert "score" not in losses


@pytest.mark.parametrize("layout", LAYOUTS)
def test_step_3d_gradients_skip_the_pose_branch(layout, images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(**LAYOUTS[layout]))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=8)
    losses = objectives_of(model).step_3d(model, images)
    assert {"rgb", "perceptual", "normal", "laplacian", "total"} <= set(losses)
    assert torch.allclose(losses["total"], sum(v for k, v in losses.items() if k != "total"))
    losses["total"].backward()
    assert grads_of(model.pose) == 0
    for module in (model.shape.field, model.shape.regressor, model.texture, model.background, model.scale):
        assert grads_of(module) > 0
    read_3d = encoders_read_by(model, ("shape", "texture", "background"))
    for i, encoder in enumerate(model.encoders):
        assert (grads_of(encoder) > 0) == (i in read_3d)


def test_neighbor_term_gradients_reach_only_shape_and_texture(images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config())
    randomize_heads(model, std=0.1)
    model.set_active_dims(shape=2, texture=8)
    inactive = Unicorn(tiny_config())  # shape code 0-dim: inactive
    assert "neighbor" not in objectives_of(inactive).step_3d(inactive, images)
    objectives = objectives_of(model)
    # memory with other viewpoints so that every sample has neighbours
    with torch.no_grad():
        other = torch.rand(6, 3, IMAGE_SIZE, IMAGE_SIZE)
        pred = model.predict(other)
        turn = azim_elev_roll_to_rotation(torch.linspace(40, 160, 6), torch.zeros(6))
        objectives.memory.push(other, pred.shape_code, pred.texture_code, turn)
    losses = objectives.step_3d(model, images)
    assert "neighbor" in losses and losses["neighbor"].item() > 0
    losses["neighbor"].backward()  # the neighbour term alone
    assert grads_of(model.shape.field) > 0 and grads_of(model.texture.generator) > 0
    assert grads_of(model.background) == 0 and grads_of(model.scale) == 0 and grads_of(model.pose) == 0
    assert len(objectives.memory) == 6 + images.shape[0]


def test_neighbor_term_is_the_swapped_reconstruction_against_the_neighbours_images(images):
    """The 3D step's neighbour term against both swaps rendered here from the model's predictions on known
    neighbours: the sample's canonical shape with its shape neighbour's scale, texture, pose and background, and its
    texture on its texture neighbour's mesh, pose and background, each against that neighbour's image."""
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"neighbor_weight": 0.5})).eval()  # eval: batch norm is the same in every call
    randomize_heads(model, std=0.1)
    vivid_textures(model)
    model.set_active_dims(shape=2, texture=8)
    objectives = objectives_of(model)
    memory, reconstruction = objectives.memory, objectives.steps["3d"].reconstruction
    B = images.shape[0]
    # renders of an ellipsoid on white from six azimuths: unlike the noise images of the batch
    shape_nbr, texture_nbr = ellipsoid_images(2 * B).split(B)
    with torch.no_grad():
        own = model.predict(images)
        z_sh, z_tx, R = own.shape_code, own.texture_code, own.poses.R[own.poses.probs.argmax(0), torch.arange(B)]
        # every entry 100 degrees away from every query (one bin: the draw cannot matter); sample b's shape
        # neighbour holds its very shape code and a far texture code, its texture neighbour the other way round
        turned = R[:1] @ azim_elev_roll_to_rotation(torch.tensor([100.0]), torch.zeros(1))
        far = 100.0 + torch.arange(B, dtype=torch.float32).unsqueeze(1)
        memory.push(
            torch.cat([shape_nbr, texture_nbr]),
            torch.cat([z_sh, z_sh + far]),
            torch.cat([z_tx + far, z_tx]),
            turned.expand(2 * B, 3, 3),
        )
        # the batch's own entries (pushed by the step) lie within min_angle of each other: never neighbours
        assert (memory.bin_of(rotation_angle_between(R.unsqueeze(1), R.unsqueeze(0))) == -1).all()
        assert (memory.bin_of(rotation_angle_between(turned, R)) == 2).all()
        s, t = model.predict(shape_nbr), model.predict(texture_nbr)
        swap_shape, _ = model.render(own.canonical_verts * s.scale.unsqueeze(1), s.texture, s.R, s.T, s.background)
        swap_texture, _ = model.render(t.verts, own.texture, t.R, t.T, t.background)
        expected = sum(reconstruction(swap_shape, shape_nbr).values()) + sum(
            reconstruction(swap_texture, texture_nbr).values()
        )
    losses = objectives.step_3d(model, images)
    assert float(expected.min()) > 0
    assert torch.allclose(losses["neighbor"], 0.5 * expected.mean(), rtol=1e-4)
    assert len(memory) == 3 * B


def test_both_steps_decrease_losses_on_synthetic_renders():
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"memory_size": 32}))
    model.set_active_dims(shape=2, texture=8)
    data = ellipsoid_images(8)
    objectives = objectives_of(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    history: dict[str, list[float]] = {"pose": [], "3d": []}
    g = torch.Generator().manual_seed(0)
    for it in range(24):
        batch = data[torch.randperm(8, generator=g)[:4]]
        optimizer.zero_grad(set_to_none=True)
        losses = objectives("pose" if it % 2 == 0 else "3d", model, batch)
        assert all(torch.isfinite(v) for v in losses.values()), losses
        losses["total"].backward()
        optimizer.step()
        history["pose" if it % 2 == 0 else "3d"].append(losses["total"].item())
    for name, values in history.items():
        first, last = sum(values[:4]) / 4, sum(values[-4:]) / 4
        assert last < 0.7 * first, (name, values)


def test_pose_step_equivariance_term_is_the_moved_batch_consistency(images):
    model = Unicorn(tiny_config(loss={"equivariance_weight": 0.5})).eval()
    randomize_heads(model)
    torch.manual_seed(3)
    losses = objectives_of(model).pose_step(model, images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "equivariance", "total"}
    torch.manual_seed(3)  # the same draws from torch's global stream
    moved, roll, shift = random_roll_shift(images, 15.0, 0.1)
    with torch.no_grad():
        expected = 0.5 * view_equivariance_loss(
            model.predict(images).poses,
            model.predict(moved).poses,
            roll,
            shift,
            model.pose,
            model.renderer.camera.focal_length,
        )
    assert float(expected) > 0 and torch.allclose(losses["equivariance"], expected, rtol=1e-5)
    losses["equivariance"].backward()
    assert grads_of(model.pose.rot_regressors) > 0 and grads_of(model.encoders[0]) > 0
    assert grads_of(model.texture) == 0
    assert "equivariance" not in objectives_of(Unicorn(tiny_config())).pose_step(model, images)


def test_pose_step_flip_term_is_the_flipped_batch_consistency(images):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(loss={"flip_weight": 0.5})).eval()  # eval: batch norm is the same in every call
    randomize_heads(model)
    losses = objectives_of(model).pose_step(model, images)
    assert set(losses) == {"rgb", "perceptual", "uniform", "flip", "total"}
    with torch.no_grad():
        expected = 0.5 * flip_consistency_loss(
            model.predict(images).poses, model.predict(images.flip(-1)).poses, model.pose.mirror_index()
        )
    assert float(expected) > 0 and torch.allclose(losses["flip"], expected, rtol=1e-5)
    losses["flip"].backward()
    assert grads_of(model.pose.proba_regressor) > 0 and grads_of(model.encoders[0]) > 0
    assert grads_of(model.texture) == 0
    # left out at weight 0 (the default, the paper's)
    assert "flip" not in objectives_of(Unicorn(tiny_config())).pose_step(model, images)
