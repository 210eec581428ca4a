"""Mixed precision (``trainer.precision=bf16-mixed``): a pose step and a 3D step under bfloat16 autocast against the
same steps in float32, on the CPU and, marked ``gpu``, on CUDA.

The encoders, the generators' layers and the VGG16 perceptual loss run in bfloat16; the pose candidates, the scale
and the renderer in float32. The bounds were chosen from measurements of these steps on the CPU, with a margin of many
times the observed differences for other kernels (CUDA's) and seeds: bfloat16 keeps 8 significant bits.

The models' batch norm uses its running statistics (eval mode), so that both runs normalise alike: with the batch
statistics of a few images the gradient at initialisation is ill-conditioned: float32 itself moves it by a
comparable amount when only the input images are rounded to bfloat16 (docs/training.md, "Mixed precision").
"""

from __future__ import annotations

import pytest
import torch

from tests.support.model import ellipsoid_images, randomize_heads, tiny_config
from unicorn.model import Unicorn
from unicorn.model.config import CODE_BRANCHES
from unicorn.objectives import Objectives
from unicorn.objectives.perceptual import _CONVS, VGGPerceptualLoss

#: the largest relative difference of a step's total loss under bfloat16 autocast
LOSS_RTOL = 5e-3
#: the smallest cosine similarity of a step's gradient (all parameters as one vector) with the float32 one
GRAD_COSINE = 0.95

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]

# randomised heads can fold meshes into more layers than faces_per_pixel: irrelevant here
pytestmark = pytest.mark.filterwarnings("ignore:some pixels had more than faces_per_pixel")


def random_vgg_weights(generator: torch.Generator) -> dict[str, torch.Tensor]:
    """A torchvision-named VGG16 state dict (up to relu3_3) with He-initialised random values."""
    state = {}
    for index, cin, cout in _CONVS:
        state[f"features.{index}.weight"] = torch.randn(cout, cin, 3, 3, generator=generator) * (2 / (9 * cin)) ** 0.5
        state[f"features.{index}.bias"] = torch.zeros(cout)
    return state


def build(device: str) -> tuple[Unicorn, Objectives, torch.Tensor]:
    """The small model at 32 px with randomised heads, every code active, the VGG16 loss (random weights)."""
    torch.manual_seed(0)
    # min_angle 0: the initial heads predict nearly one rotation for all images, and neighbours must still be found
    cfg = tiny_config(loss={"perceptual": "structural", "perceptual_weight": 1.0, "min_angle": 0.0})
    model = Unicorn(cfg)
    randomize_heads(model)
    model.set_active_dims(**{name: cfg[name]["code_dim"] for name in CODE_BRANCHES if cfg[name] is not None})
    objectives = Objectives.from_config(cfg["loss"], model)
    # the perceptual module is shared by both steps' reconstruction losses
    objectives.steps["pose"].reconstruction.perceptual = VGGPerceptualLoss(
        random_vgg_weights(torch.Generator().manual_seed(1))
    )
    model.to(device).eval()  # batch norm with running statistics (module docstring)
    objectives.to(device)
    return model, objectives, ellipsoid_images(6).to(device)


def step(
    model: Unicorn, objectives: Objectives, images: torch.Tensor, kind: str, bf16: bool
) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
    """One step's terms and its gradients (flat, float32, by parameter name), from the same random state and
    neighbour memory whatever ran before."""
    memory = objectives.memory.state()
    torch.manual_seed(2)  # the neighbour loss draws its viewpoint bins
    model.zero_grad(set_to_none=True)
    with torch.autocast(images.device.type, dtype=torch.bfloat16, enabled=bf16):
        losses = objectives(kind, model, images)
    losses["total"].backward()
    objectives.memory.load_state(memory)
    grads = {name: p.grad.float().flatten() for name, p in model.named_parameters() if p.grad is not None}
    return {name: float(value.detach()) for name, value in losses.items()}, grads


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kind", ["pose", "3d"])
def test_bf16_steps_are_close_to_float32(device, kind):
    model, objectives, images = build(device)
    reference, ref_grads = step(model, objectives, images, kind, bf16=False)
    mixed, grads = step(model, objectives, images, kind, bf16=True)
    assert mixed.keys() == reference.keys()
    assert grads.keys() == ref_grads.keys()  # the same parameters are reached
    grad, ref_grad = torch.cat(list(grads.values())), torch.cat(list(ref_grads.values()))
    if kind == "3d":
        assert reference["neighbor"] > 0
    loss_error = abs(mixed["total"] - reference["total"]) / abs(reference["total"])
    cosine = float(torch.nn.functional.cosine_similarity(grad, ref_grad, dim=0))
    print(f"{device} {kind}: loss relative error {loss_error:.2e}, gradient cosine {cosine:.5f}")
    assert loss_error < LOSS_RTOL, (reference, mixed)
    assert cosine > GRAD_COSINE


def test_pose_candidates_are_float32_under_autocast():
    model, _, images = build("cpu")
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        pred = model.predict(images)
    assert pred.R.dtype == pred.T.dtype == pred.scale.dtype == pred.poses.probs.dtype == torch.float32
    eye = torch.eye(3).expand_as(pred.R)
    assert torch.allclose(pred.R @ pred.R.transpose(1, 2), eye, atol=1e-5)
