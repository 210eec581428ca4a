"""A training checkpoint written by an earlier version of the library loads and reproduces its predictions and losses.

The fixture (tests/fixtures/README.md) holds a tiny run's checkpoint and the values that version computed from it:
what the model predicts and renders for a fixed input, and the pose- and 3D-step losses of the training module
restored from the checkpoint (neighbour memory and random states included).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from tests.support.model import randomize_heads, tiny_config
from unicorn.io.checkpoints import load_model
from unicorn.lit import UnicornLitModule
from unicorn.model import Unicorn

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
# the same machine reproduces the values exactly; the tolerance admits other CPUs' kernels
TOL = {"rtol": 1e-4, "atol": 1e-5}


@pytest.fixture(scope="module")
def expected() -> dict:
    return torch.load(FIXTURES / "tiny_run_expected.pt", weights_only=False)


def _outputs(model: Unicorn, x: torch.Tensor) -> dict[str, torch.Tensor]:
    pred = model.predict(x)
    rgb, alpha = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    names = ("shape_code", "texture_code", "background_code", "canonical_verts", "scale", "verts", "texture")
    out = {k: getattr(pred, k) for k in (*names, "background", "R", "T")}
    out.update(probs=pred.poses.probs, rgb=rgb, alpha=alpha)
    return {k: v for k, v in out.items() if v is not None}


def _assert_same(got: dict[str, torch.Tensor], want: dict[str, torch.Tensor]) -> None:
    assert set(got) == set(want)
    for name, value in want.items():
        torch.testing.assert_close(got[name].detach(), value, **TOL, msg=lambda m, n=name: f"{n}: {m}")


def test_checkpoint_loads_and_predicts_the_same(expected):
    model, _ = load_model(FIXTURES / "tiny_run.ckpt")
    with torch.no_grad():
        _assert_same(_outputs(model, expected["input"]), expected["eval"])


def test_restored_training_module_gives_the_same_losses(expected):
    ckpt = torch.load(FIXTURES / "tiny_run.ckpt", map_location="cpu", weights_only=False)
    module = UnicornLitModule(**ckpt["hyper_parameters"])
    module.load_state_dict(ckpt["state_dict"])
    module.on_load_checkpoint(ckpt)
    module.on_train_start()  # restores the neighbour memory and the random states
    module.train()
    x = expected["input"]
    steps = {
        "pose": lambda: module.objectives("pose", module.model, x),
        "3d": lambda: module.objectives("3d", module.model, x),
        "3d_average": lambda: module.objectives("3d", module.model, x, average_texture=True),
    }
    for name, step in steps.items():
        losses = step()
        got = {k: v.detach() for k, v in losses.items()} | {"probs": losses.probs}
        _assert_same(got, expected[f"step_{name}"])


def _without(mapping: dict, key: str) -> dict:
    return {k: v for k, v in mapping.items() if k != key}


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda u: {**u, "ranks": []}, r"resume state's 'unicorn' entry must be a dict whose 'ranks' is a non-empty"),
        (lambda u: [u], r"resume state's 'unicorn' entry must be a dict"),
        (lambda u: {**u, "ranks": [_without(u["ranks"][0], "rng")]}, r"resume state's ranks\[0\]\.rng must be"),
        (lambda u: {**u, "ranks": [_without(u["ranks"][0], "memory")]}, r"ranks\[0\]\.memory must be a dict of"),
        (
            lambda u: {**u, "ranks": [{**u["ranks"][0], "rng": {**u["ranks"][0]["rng"], "torch": torch.zeros(3)}}]},
            r"ranks\[0\]\.rng must be torch, numpy and python random states \(TypeError\)",
        ),
    ],
    ids=["no-ranks", "a-list", "no-rng", "no-memory", "bad-torch-state"],
)
def test_a_malformed_resume_state_is_refused_before_anything_is_restored(change, message):
    from unicorn.io.serialization import CheckpointError

    ckpt = torch.load(FIXTURES / "tiny_run.ckpt", map_location="cpu", weights_only=False)
    module = UnicornLitModule(**ckpt["hyper_parameters"])
    before = torch.get_rng_state()
    with pytest.raises(CheckpointError, match=message) as info:
        module.on_load_checkpoint({**ckpt, "unicorn": change(ckpt["unicorn"])})
    assert "\n" not in str(info.value) and torch.equal(torch.get_rng_state(), before)
    memory = ckpt["unicorn"]["ranks"][0]["memory"]
    broken = {**ckpt["unicorn"], "ranks": [{**ckpt["unicorn"]["ranks"][0], "memory": _without(memory, "images")}]}
    module.on_load_checkpoint({**ckpt, "unicorn": broken})  # tensors of the right types: found when restored
    with pytest.raises(CheckpointError, match=r"resume state's neighbour memory cannot be restored: a neighbour"):
        module.on_train_start()


@pytest.mark.parametrize("composite", ["direct", "reference"])
def test_background_model_renders_the_same(expected, composite):
    torch.manual_seed(0)
    cfg = tiny_config("real", encoder={"width": 4})
    cfg["renderer"]["composite"] = composite
    model = Unicorn(cfg)
    randomize_heads(model)
    model.eval()
    with torch.no_grad():
        _assert_same(_outputs(model, expected["input"]), expected[f"background_{composite}"])
