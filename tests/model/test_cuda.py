"""The CUDA path of the model and its objectives: both training steps give the CPU's losses and gradients (run where
CUDA is)."""

from __future__ import annotations

import copy

import pytest
import torch

from tests.support.model import randomize_heads, tiny_config
from unicorn.model import Unicorn
from unicorn.objectives import Objectives

pytestmark = pytest.mark.gpu


@pytest.mark.parametrize("family", ["real", "shapenet"])
def test_training_steps_match_cpu(family, images):
    torch.manual_seed(0)
    cpu = Unicorn(tiny_config(family))
    randomize_heads(cpu)
    cpu.set_active_dims(shape=4, texture=4, background=4)
    gpu = copy.deepcopy(cpu).cuda()
    objectives = {"cpu": Objectives.from_config(cpu.config["loss"], cpu)}
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
            torch.testing.assert_close(b[key].cpu(), a[key].detach(), rtol=1e-3, atol=1e-4, msg=f"{name} {key}")
        for (n, p), q in zip(cpu.named_parameters(), gpu.parameters()):
            assert (p.grad is None) == (q.grad is None), n
            if p.grad is not None:
                torch.testing.assert_close(q.grad.cpu(), p.grad, rtol=1e-2, atol=1e-4, msg=f"{name} grad {n}")
