"""The objectives' steps inside :func:`unicorn.hostsync.sync_free`: the same losses and gradients as the default
steps, no host read and, on another device, no host tensor (:mod:`tests.support.syncs`)."""

from __future__ import annotations

import collections
import copy

import pytest
import torch

from tests.support.model import IMAGE_SIZE, randomize_heads, tiny_config
from tests.support.syncs import HostTensorRecorder, outside, record_syncs
from unicorn.checks import check_mesh
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.hostsync import is_sync_free, sync_free
from unicorn.model import Unicorn
from unicorn.objectives import Objectives
from unicorn.render import OverflowCounter
from unicorn.render.raster import check_pose_inputs
from unicorn.render.rasterizer import MeshRasterizer

#: the optional terms of the pose step (each off by default), all at once, under each pose objective
OPTIONAL_TERMS = {
    "expected": {"spacing_weight": 0.1, "flip_weight": 0.1, "equivariance_weight": 0.1, "viewpoint": "renders"},
    "assigned": {"pose_objective": "assigned", "viewpoint": "renders"},
    "sampled": {"pose_objective": "sampled"},
}


def _setup(seed: int = 0, **loss):
    torch.manual_seed(seed)
    model = Unicorn(tiny_config())
    randomize_heads(model, std=0.1)
    model.set_active_dims(shape=2, texture=8)
    objectives = Objectives.from_config({**model.config["loss"], "neighbor_weight": 1.0, **loss}, model)
    with torch.no_grad():  # memory with other viewpoints so that every sample has neighbours
        other = torch.rand(6, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(2))
        pred = model.predict(other)
        turn = azim_elev_roll_to_rotation(torch.linspace(40, 160, 6), torch.zeros(6))
        objectives.memory.push(other, pred.shape_code, pred.texture_code, turn)
    return model, objectives


def _step(model, objectives, kind, images, free: bool):
    model.zero_grad(set_to_none=True)
    torch.manual_seed(7)  # the neighbours' bins are drawn from the global stream
    with sync_free(free):
        losses = objectives(kind, model, images, iteration=5)
        losses["total"].backward()
    grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    return {k: v.detach() for k, v in losses.items()}, grads


@pytest.mark.parametrize("kind", ["pose", "3d"])
def test_sync_free_steps_give_the_default_losses_and_gradients(kind, images):
    model, objectives = _setup()
    twin = copy.deepcopy((model, objectives))
    default = _step(model, objectives, kind, images, False)
    # the rasterizers' fixed buffers as the default step sized them
    rasterizers = [[m for m in net.modules() if isinstance(m, MeshRasterizer)] for net in (model, twin[0])]
    for a, b in zip(*rasterizers):
        b.buffers = dict(a.buffers)
    assert any(r.buffers for r in rasterizers[1])
    free = _step(*twin, kind, images, True)
    assert not any(r.grow_buffers() for r in rasterizers[1])  # large enough: nothing dropped
    assert default[0].keys() == free[0].keys() and default[1].keys() == free[1].keys()
    for name, value in default[0].items():
        torch.testing.assert_close(free[0][name], value, rtol=1e-6, atol=1e-7, msg=name)
    for name, value in default[1].items():
        torch.testing.assert_close(free[1][name], value, rtol=1e-5, atol=1e-7, msg=name)


def test_sync_free_steps_read_nothing_back(images):
    model, objectives = _setup()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4, fused=True)
    for i, kind in enumerate(["pose", "3d", "pose", "3d"]):
        # the first steps fill the caches and size the rasterizer's buffers; training counts the overflow
        with record_syncs() as rec, sync_free(i >= 2), OverflowCounter():
            opt.zero_grad(set_to_none=True)
            objectives(kind, model, images, iteration=i)["total"].backward()
            opt.step()
        left = outside(rec.syncs)
        assert bool(left) == (i < 2), (kind, collections.Counter(left))


@pytest.mark.filterwarnings("ignore:.*an autograd kernel was not registered:UserWarning")  # meta kernels
@pytest.mark.parametrize("terms", [None, *OPTIONAL_TERMS])
def test_sync_free_steps_on_another_device_make_no_host_tensor(images, terms):
    # the meta device stands in for CUDA here: the same Python, shapes and autograd without values, so that a
    # tensor on the host (made there, a draw, or a module's constant: copied to the device, where the host waits and
    # CUDA graphs cannot capture) shows
    model, objectives = _setup(**OPTIONAL_TERMS.get(terms, {}))
    for i, kind in enumerate(["pose", "3d"]):  # the checked steps, on the CPU: they size the fixed buffers
        with OverflowCounter():
            objectives(kind, model, images, iteration=i)["total"].backward()
    model.to("meta")
    objectives.to("meta")
    assert objectives.memory.R is not None and objectives.memory.R.device.type == "meta"  # the memory follows
    images = images.to("meta")
    for i, kind in enumerate(["pose", "3d"], start=2):
        model.zero_grad(set_to_none=True)
        with sync_free(), OverflowCounter() as counter, HostTensorRecorder() as host, record_syncs() as reads:
            losses = objectives(kind, model, images, iteration=i)
            losses["total"].backward()
        assert not host.syncs, (kind, collections.Counter(map(str, host.syncs)))
        assert not reads.syncs, (kind, collections.Counter(map(str, reads.syncs)))
        assert {v.device.type for v in losses.values()} == {"meta"}
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        assert grads and {g.device.type for g in grads} == {"meta"}
        assert {over.device.type for over, _ in counter.counts.values()} == {"meta"}  # counted on the device
    assert objectives.memory.R is not None and objectives.memory.R.device.type == "meta"


def test_sync_free_neighbour_loss_masks_the_samples_without_neighbours(images):
    model, objectives = _setup()
    objectives.memory.load_state({k: None for k in objectives.memory.state()})  # empty: nobody has neighbours
    for free in (False, True):
        with sync_free(free):
            losses = objectives("3d", model, images, iteration=5)
        assert losses["neighbor"].item() == 0.0


def test_value_checks_are_skipped_inside_sync_free():
    verts, faces = torch.zeros(1, 3, 3), torch.tensor([[0, 1, 5]])
    with pytest.raises(ValueError, match="face indices"):
        check_mesh(verts, faces)
    R, T = torch.eye(3).expand(1, 3, 3), torch.full((1, 3), float("nan"))
    with pytest.raises(ValueError, match="T contains NaN"):
        check_pose_inputs(R, T, 1)
    with sync_free(), record_syncs() as rec:
        assert is_sync_free()
        check_mesh(verts, faces, finite=True)
        check_pose_inputs(R, T, 1)
        with pytest.raises(ValueError, match="verts"):
            check_mesh(verts[0], faces)  # shapes are still checked
    assert not rec.syncs and not is_sync_free()
