"""Test-time refinement: the objective decreases, the prior holds, zero steps, determinism, batching, parts."""

from __future__ import annotations

import copy
import re

import pytest
import torch

from tests.support.model import ellipsoid_images, randomize_heads, tiny_config
from unicorn.model import Unicorn
from unicorn.objectives.loss_factory import build_losses
from unicorn.objectives.refine import PARTS, RefineOptions, refine

pytestmark = pytest.mark.filterwarnings("ignore:some pixels had more than faces_per_pixel")

FIELDS = ("shape_code", "texture_code", "background_code", "canonical_verts", "scale", "verts", "texture")
FIELDS += ("background", "R", "T")


@pytest.fixture(scope="module")
def model() -> Unicorn:
    torch.manual_seed(0)
    m = Unicorn(tiny_config(template={"level": 2}, texture={"size": 16}))
    randomize_heads(m)
    m.set_active_dims(shape=m.shape.code_dim, texture=m.texture.code_dim, background=m.background.code_dim)
    return m.eval()


@pytest.fixture(scope="module")
def targets() -> torch.Tensor:
    return ellipsoid_images(3)


def test_zero_steps_is_the_prediction(model: Unicorn, targets: torch.Tensor) -> None:
    with torch.no_grad():
        pred = model.predict(targets)
    out = refine(model, targets, RefineOptions(steps=0))
    for name in FIELDS:
        assert torch.equal(getattr(out.prediction, name), getattr(pred, name)), name
    assert out.losses.shape == (1, 3)


def test_an_initial_prediction_of_another_batch_is_refused_naming_both_sizes(
    model: Unicorn, targets: torch.Tensor
) -> None:
    with torch.no_grad():
        two = model.predict(targets[:2])
    with pytest.raises(ValueError, match=r"^initial holds 2 predictions for 3 images: give refine the network's"):
        refine(model, targets, RefineOptions(steps=1), initial=two)


def test_objective_decreases_and_weights_stay(model: Unicorn, targets: torch.Tensor) -> None:
    state = {k: v.clone() for k, v in model.state_dict().items()}
    model.train()
    out = refine(model, targets, RefineOptions(steps=20, codes_first=0.25))
    assert out.losses.shape == (21, 3)
    assert (out.losses[-1] < 0.9 * out.losses[0]).all(), out.losses[[0, -1]]
    assert model.training and all(p.requires_grad for p in model.parameters())  # mode and flags given back
    model.eval()
    for k, v in model.state_dict().items():
        assert torch.equal(v, state[k]), k


def test_huge_prior_keeps_the_prediction(model: Unicorn, targets: torch.Tensor) -> None:
    weights = dict(code_weight=1e8, colour_weight=1e8, texture_weight=1e8, vertex_weight=1e8, pose_weight=1e8)
    every = dict(steps=30, codes_first=0.0, parts=tuple(PARTS), lr_shape_code=0.1)
    out = refine(model, targets, RefineOptions(**every, **weights))
    free = refine(model, targets, RefineOptions(**every))
    for name in ("verts", "texture", "R", "T", "background"):
        kept = (getattr(out.prediction, name) - getattr(out.initial, name)).abs().max()
        moved = (getattr(free.prediction, name) - getattr(free.initial, name)).abs().max()
        # Adam's first steps move every variable by about lr whatever the weight; the prior pulls them back
        assert kept < 0.02 * moved, (name, kept, moved)


def test_deterministic(model: Unicorn, targets: torch.Tensor) -> None:
    options = RefineOptions(steps=6, parts=tuple(PARTS), lr_shape_code=0.1)  # every variable moves
    a = refine(model, targets, options)
    b = refine(model, targets, options)
    for name in FIELDS:
        assert torch.equal(getattr(a.prediction, name), getattr(b.prediction, name)), name


def test_under_no_grad_the_steps_compute_their_gradients(model: Unicorn, targets: torch.Tensor) -> None:
    # beside model.predict, as an evaluation loop calls it: the same refinement as with gradients enabled
    options = RefineOptions(steps=4, parts=tuple(PARTS), lr_shape_code=0.1)
    with torch.no_grad():
        pred = model.predict(targets)
        quiet = refine(model, targets, options, initial=pred)
        assert not torch.is_grad_enabled()  # given back as it was
    loud = refine(model, targets, options, initial=pred)
    assert torch.equal(quiet.losses, loud.losses)
    for name in FIELDS:
        assert torch.equal(getattr(quiet.prediction, name), getattr(loud.prediction, name)), name


def test_inference_mode_is_one_line_naming_it(model: Unicorn, targets: torch.Tensor) -> None:
    with torch.inference_mode():
        assert refine(model, targets, RefineOptions(steps=0)).losses.shape == (1, 3)  # no step: nothing to compute
        with pytest.raises(RuntimeError, match=r"^refine takes gradient steps, which torch.inference_mode\(\) forb"):
            refine(model, targets, RefineOptions(steps=1))


def test_batch_equals_one_image_at_a_time(model: Unicorn, targets: torch.Tensor) -> None:
    # in float64: Adam's normalised steps turn float32 rounding (batched kernels sum in another order) into
    # visible differences on variables whose gradient is near 0, and in float64 too they grow about fivefold a step
    # (from 1e-11 after the first): four steps, two on the codes and two on every part, keep them below 1e-8
    model, targets = copy.deepcopy(model).double(), targets.double()
    options = RefineOptions(steps=4, codes_first=0.5, parts=tuple(PARTS), lr_shape_code=0.1)
    batch = refine(model, targets, options)
    for i in range(targets.shape[0]):
        alone = refine(model, targets[i : i + 1], options)
        for name in FIELDS:
            torch.testing.assert_close(
                getattr(alone.prediction, name)[0], getattr(batch.prediction, name)[i], atol=1e-7, rtol=1e-7
            )
        torch.testing.assert_close(alone.losses[:, 0], batch.losses[:, i], atol=1e-9, rtol=1e-7)


@pytest.mark.parametrize(
    ("part", "moves", "stays"),
    [
        ("codes", ("shape_code", "texture_code", "background_code", "verts", "texture", "background"), ("R", "T")),
        ("texture", ("texture",), ("verts", "R", "T", "background", "texture_code")),
        ("vertices", ("verts", "scale"), ("texture", "R", "T", "shape_code")),
        ("pose", ("R", "T"), ("verts", "texture", "background")),
    ],
)
def test_each_part_moves_its_own_variables(
    model: Unicorn, targets: torch.Tensor, part: str, moves: tuple[str, ...], stays: tuple[str, ...]
) -> None:
    out = refine(model, targets, RefineOptions(steps=3, parts=(part,), lr_shape_code=0.1))
    for name in moves:
        assert not torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name
    for name in stays:
        assert torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name


def test_codes_first_holds_the_residuals(model: Unicorn, targets: torch.Tensor) -> None:
    # all steps on the codes: the mesh is exactly the decoded shape code, the pose the network's
    out = refine(model, targets, RefineOptions(steps=4, codes_first=1.0))
    p = out.prediction
    with torch.no_grad():
        canonical = model.template.verts + model.shape(model.template.verts, p.shape_code)
    assert torch.equal(p.canonical_verts, canonical)
    assert torch.equal(p.R, out.initial.R) and torch.equal(p.T, out.initial.T)
    assert torch.equal(p.scale, out.initial.scale)


def test_kept_shape_code(model: Unicorn, targets: torch.Tensor) -> None:
    # lr_shape_code=0: the codes part moves the texture and background codes, never the shape
    out = refine(model, targets, RefineOptions(steps=4, parts=("codes",), lr_shape_code=0.0))
    for name in ("shape_code", "canonical_verts", "verts"):
        assert torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name
    for name in ("texture_code", "background_code", "texture"):
        assert not torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name
    # its own rate: a smaller one moves the shape code less than the other codes' rate does
    slow = refine(model, targets, RefineOptions(steps=4, parts=("codes",), lr_shape_code=0.01, lr_codes=0.1))
    fast = refine(model, targets, RefineOptions(steps=4, parts=("codes",), lr_shape_code=0.1, lr_codes=0.1))
    moved = [(r.prediction.shape_code - r.initial.shape_code).abs().max() for r in (slow, fast)]
    assert 0 < moved[0] < 0.2 * moved[1], moved


def test_defaults_refine_the_appearance_and_outline(model: Unicorn, targets: torch.Tensor) -> None:
    # one view constrains the colours and the outline, not the hidden side's shape: the defaults keep the shape
    # code and the pose, and move the vertices only a little (a strong prior)
    out = refine(model, targets, RefineOptions(steps=4))
    for name in ("shape_code", "R", "T"):
        assert torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name
    for name in ("texture_code", "background_code", "texture", "background", "verts"):
        assert not torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name
    weak = refine(model, targets, RefineOptions(steps=4, vertex_weight=0.0))
    moved = (out.prediction.verts - out.initial.verts).norm(dim=-1).mean()
    assert moved < (weak.prediction.verts - weak.initial.verts).norm(dim=-1).mean()


def test_pose_part_and_bad_options(model: Unicorn, targets: torch.Tensor) -> None:
    out = refine(model, targets[:1], RefineOptions(steps=2, parts=("pose",), lr_pose=0.01))
    assert out.losses.shape == (3, 1)
    with pytest.raises(ValueError, match=r"unknown refinement part\(s\) \['colour'\]"):
        RefineOptions(parts=("colour",))
    # one string: a name of a set of parts, or names joined by commas, as --refine-parts takes them
    assert RefineOptions(parts="all").parts == tuple(PARTS)
    assert RefineOptions(parts="default").parts == RefineOptions().parts == ("codes", "texture", "vertices")
    assert RefineOptions(parts="codes, pose").parts == ("codes", "pose")
    for parts in ("", ()):
        with pytest.raises(ValueError, match="no refinement part"):
            RefineOptions(parts=parts)
    for bad in (float("nan"), float("inf"), "0.1", None):
        with pytest.raises(ValueError, match=rf"^lr_codes must be a finite number >= 0, got {bad!r}$"):
            RefineOptions(lr_codes=bad)
    with pytest.raises(ValueError, match="steps"):
        RefineOptions(steps=-1)
    with pytest.raises(ValueError, match="images must have shape"):
        refine(model, targets[:, :, :16])
    assert set(PARTS) == {"codes", "texture", "vertices", "pose"}


def test_a_whole_float_is_a_step_count_and_other_counts_are_one_line(model: Unicorn, targets: torch.Tensor) -> None:
    # 2.0 as a number read from a JSON or YAML file gives it: the same refinement as 2
    options = RefineOptions(steps=2.0, parts=("texture",))
    assert options.steps == 2 and isinstance(options.steps, int)
    out = refine(model, targets[:1], options)
    assert torch.equal(out.losses, refine(model, targets[:1], RefineOptions(steps=2, parts=("texture",))).losses)
    for bad in (2.5, "2", None, True, float("nan")):
        with pytest.raises(ValueError, match=rf"^steps must be a whole number, got {re.escape(repr(bad))}$"):
            RefineOptions(steps=bad)
    for bad in ("0.5", None, float("nan"), 1.5):
        message = rf"^codes_first must be a number in \[0, 1\], got {re.escape(repr(bad))}$"
        with pytest.raises(ValueError, match=message):
            RefineOptions(codes_first=bad)


NO_PRIOR = dict(code_weight=0.0, colour_weight=0.0, texture_weight=0.0, vertex_weight=0.0, pose_weight=0.0)


@pytest.mark.parametrize(
    "options",
    [
        # overshoots: image 0 ends above its start (0.641 > 0.631), the others end at their lowest
        RefineOptions(steps=6, parts=("texture",), lr_texture=1.0, **NO_PRIOR),
        # oscillates: images 0 and 1 are lowest at step 2 and end above it
        RefineOptions(steps=6, parts=("vertices",), lr_vertices=0.3, **NO_PRIOR),
    ],
    ids=["texture", "vertices"],
)
def test_returns_the_lowest_iterate_and_its_objective(
    model: Unicorn, targets: torch.Tensor, options: RefineOptions
) -> None:
    out = refine(model, targets, options)
    lowest = out.losses.min(0)
    assert (out.losses[-1] > lowest.values).any(), out.losses  # the setting overshoots: the last is not the lowest
    assert (out.objective <= out.losses[0]).all(), (out.objective, out.losses)  # never worse than the network's
    assert torch.equal(out.objective, lowest.values) and torch.equal(out.best_step, lowest.indices)
    # without priors the objective is the image terms and the mesh regularisers: evaluated afresh on the result
    p = out.prediction
    fns = build_losses(model.config["loss"], model.template)
    with torch.no_grad():
        rec, _ = model.render(p.verts, p.texture, p.R, p.T, p.background)
        fresh = sum(fns.reconstruction(rec, targets).values()) + sum(
            fns.regularizer(p.verts, reduction="none").values()
        )
    torch.testing.assert_close(fresh, out.objective, rtol=1e-5, atol=1e-7)
    for i, step in enumerate(out.best_step.tolist()):
        kept = [torch.equal(getattr(p, name)[i], getattr(out.initial, name)[i]) for name in ("verts", "texture")]
        assert all(kept) == (step == 0), (i, step, kept)


def test_a_prediction_that_fits_its_image_is_kept(model: Unicorn, targets: torch.Tensor) -> None:
    # the model's own rendering of its prediction: every step of the defaults (Adam's first moves each texel by
    # about lr_texture, which the texel prior charges) ends above the start, so the network's prediction is returned
    with torch.no_grad():
        pred = model.predict(targets)
        own, _ = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    out = refine(model, own, RefineOptions(steps=6))
    assert (out.losses[1:] > out.losses[0]).all(), out.losses
    assert torch.equal(out.objective, out.losses[0]) and out.best_step.tolist() == [0, 0, 0]
    for name in FIELDS:
        assert torch.equal(getattr(out.prediction, name), getattr(out.initial, name)), name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(model: Unicorn, targets: torch.Tensor) -> None:
    # float64, as the batching test: Adam's normalised steps would turn the devices' rounding into differences
    model, targets, options = copy.deepcopy(model).double(), targets.double(), RefineOptions(steps=3)
    cpu = refine(model, targets, options)
    gpu = refine(model.cuda(), targets.cuda(), options)
    assert gpu.prediction.verts.device.type == "cuda"
    for name in ("verts", "texture", "R", "T"):
        torch.testing.assert_close(getattr(gpu.prediction, name).cpu(), getattr(cpu.prediction, name))
