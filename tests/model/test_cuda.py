"""The CUDA path of the model and its objectives: both training steps give the CPU's losses and gradients (run where
CUDA is).

Compared in float64. In float32 the pose step's gradients carry rounding errors of a few per cent on both devices
(the CPU's float32 gradients differ from its float64 ones by as much: the batch norms over 3 images and the
candidates' weighted sum amplify rounding), so float32 tolerances loose enough to pass would hide a wrong CUDA path.
"""

from __future__ import annotations

import copy

import pytest
import torch

from tests.support.model import randomize_heads, tiny_config
from unicorn.model import Unicorn
from unicorn.objectives import Objectives

pytestmark = pytest.mark.gpu


def _assert_close(actual: torch.Tensor, expected: torch.Tensor, what: str, **tolerances: float) -> None:
    """``torch.testing.assert_close`` whose message names ``what`` and keeps torch's account of the mismatch."""
    torch.testing.assert_close(actual, expected, msg=lambda detail: f"{what}: {detail}", **tolerances)


@pytest.mark.parametrize("family", ["real", "shapenet"])
def test_training_steps_match_cpu(family, images):
    torch.manual_seed(0)
    cpu = Unicorn(tiny_config(family)).double()
    images = images.double()
    randomize_heads(cpu)
    cpu.set_active_dims(shape=4, texture=4, background=4)
    gpu = copy.deepcopy(cpu).cuda()
    objectives = {"cpu": Objectives.from_config(cpu.config["loss"], cpu).double()}
    objectives["gpu"] = copy.deepcopy(objectives["cpu"]).cuda()
    for name in ("pose", "3d"):
        for _ in range(2):  # the second 3D step finds neighbours in the memory filled by the first
            cpu.zero_grad(set_to_none=True)
            gpu.zero_grad(set_to_none=True)
            a = objectives["cpu"](name, cpu, images)
            b = objectives["gpu"](name, gpu, images.cuda())
            a["total"].backward()
            b["total"].backward()
        assert a.keys() == b.keys()
        for key in a:
            _assert_close(b[key].cpu(), a[key].detach(), f"{name} {key}", rtol=1e-7, atol=1e-9)
        for (n, p), q in zip(cpu.named_parameters(), gpu.parameters()):
            assert (p.grad is None) == (q.grad is None), n
            if p.grad is not None:
                _assert_close(q.grad.cpu(), p.grad, f"{name} grad {n}", rtol=1e-5, atol=1e-8)
