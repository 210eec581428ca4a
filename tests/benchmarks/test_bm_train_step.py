"""benchmarks/bm_train_step.py: the timed modules' hooks and the pipelined steps."""

from __future__ import annotations

import pytest
import torch

from tests.support.benchmarks import load_script, unload_script


@pytest.fixture(scope="module")
def step_bm():
    yield load_script("bm_train_step")
    unload_script("bm_train_step")


def test_a_switched_off_timer_neither_waits_nor_times(step_bm):
    waits = []
    timer = step_bm.ComponentTimer(lambda: waits.append(1))
    inner, outer = torch.nn.Linear(2, 2), torch.nn.Sequential(torch.nn.Linear(2, 2))
    timer.attach("encoder", outer)
    timer.attach("encoder", inner)
    x = torch.ones(1, 2)
    timer.enabled = False
    outer(x)
    with timer.region("neighbour"):
        inner(x)
    assert waits == [] and dict(timer.totals) == {}
    timer.enabled = True
    outer(x)
    with timer.region("neighbour"):
        inner(x)  # inside a region: counted in the region's group only
    assert len(waits) == 4 and set(timer.totals) == {"encoder", "neighbour"}


def test_pipelined_steps_run_back_to_back_each_from_fresh_gradients(step_bm):
    torch.manual_seed(0)
    layer = torch.nn.Linear(3, 1)
    opt = torch.optim.SGD(layer.parameters(), lr=0.1)
    x = torch.randn(8, 3)
    seen = []

    def forward(k):
        seen.append(k)
        return {"total": layer(x).square().mean()}

    twin = torch.nn.Linear(3, 1)
    twin.load_state_dict(layer.state_dict())
    twin_opt = torch.optim.SGD(twin.parameters(), lr=0.1)
    for _ in range(3):  # the same steps by hand: zero_grad, backward, step
        twin_opt.zero_grad()
        twin(x).square().mean().backward()
        twin_opt.step()
    seconds = step_bm.pipelined(forward, opt, "cpu", 3)
    assert seen == [0, 1, 2] and seconds > 0
    for a, b in zip(layer.parameters(), twin.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
