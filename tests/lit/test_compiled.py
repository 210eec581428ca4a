"""The training step's forward compiled whole (:mod:`unicorn.lit.compiled`): one graph per step kind without a
graph break, no new graph once warm, and the eager steps' losses and gradients (traced and differentiated without
generated code: the ``aot_eager`` backend)."""

from __future__ import annotations

import copy

import pytest
import torch
from torch._dynamo.backends.registry import lookup_backend
from torch._dynamo.utils import counters

from tests.support.model import IMAGE_SIZE, randomize_heads, tiny_config
from unicorn.hostsync import sync_free
from unicorn.lit.compiled import CompiledStep
from unicorn.model import Unicorn
from unicorn.objectives import Objectives
from unicorn.render import OverflowCounter

BATCH = 4


@pytest.fixture
def images() -> torch.Tensor:
    return torch.rand(BATCH, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(1))


def _setup():
    torch.manual_seed(0)
    model = Unicorn(tiny_config())
    randomize_heads(model, std=0.1)
    model.set_active_dims(shape=2, texture=8)
    # a memory of one batch (full from the first push: its size does not change the graph); one viewpoint bin (the
    # neighbours' bin draw, torch.multinomial, which a compiled graph draws from the random stream otherwise than
    # eagerly, has one outcome)
    loss = {**model.config["loss"], "neighbor_weight": 1.0, "n_bins": 1, "memory_size": BATCH}
    return model, Objectives.from_config(loss, model)


def _run(model, objectives, forward, kind, images, step):
    """One step's losses and gradients (``forward`` None: the eager objectives)."""
    model.zero_grad(set_to_none=True)
    torch.manual_seed(100 + step)
    with sync_free(forward is not None), OverflowCounter():
        if forward is None:
            losses = objectives(kind, model, images, iteration=step)
        else:
            losses = forward(kind, images, False, step)
        losses["total"].backward()
    grads = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    return {k: v.detach().clone() for k, v in losses.items()}, grads


def test_a_compiled_step_is_one_graph_and_gives_the_eager_losses_and_gradients(images):
    model, objectives = _setup()
    twin = copy.deepcopy((model, objectives))
    graphs = []
    aot_eager = lookup_backend("aot_eager")

    def counting(gm, example_inputs):
        graphs.append(gm)
        return aot_eager(gm, example_inputs)

    compiled = CompiledStep(twin[1], twin[0], backend=counting, copy_outputs=True)  # the copies CUDA graphs need
    counters.clear()
    seen = []
    for step, kind in enumerate(["pose", "3d"] * 3):
        checked = step < 2  # the trainer's first steps: eager, with their reads (they size the fixed buffers)
        losses, grads = _run(model, objectives, None, kind, images, step)
        got_losses, got_grads = _run(*twin, None if checked else compiled, kind, images, step)
        seen.append(len(graphs))
        assert got_losses.keys() == losses.keys() and got_grads.keys() == grads.keys()
        for name, value in losses.items():
            torch.testing.assert_close(got_losses[name], value, rtol=1e-5, atol=1e-6, msg=f"{step} {name}")
        for name, value in grads.items():  # float32 rounding of another order of the same operations
            scale = value.abs().max().clamp_min(1e-12)
            assert (got_grads[name] - value).abs().max() <= 1e-4 * scale, (step, name)
        # a plain update, and both at the same state for the next step
        with torch.no_grad():
            for p in model.parameters():
                if p.grad is not None:
                    p -= 0.05 * p.grad
            # in place: load_state_dict would drop the code masks' host copies, which the checked steps refill
            for a, b in zip([*model.parameters(), *model.buffers()], [*twin[0].parameters(), *twin[0].buffers()]):
                b.copy_(a)
        twin[1].memory.load_state(objectives.memory.state())
    assert not counters["graph_break"], dict(counters["graph_break"])  # the whole forward in one graph
    assert seen == [0, 0, 1, 2, 2, 2]  # one graph per step kind, none after
