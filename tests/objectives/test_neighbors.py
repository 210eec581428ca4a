"""Neighbour memory: bins, self-exclusion, empty bins, the ring of the newest entries, undo, saved states and moves."""

from __future__ import annotations

import pytest
import torch

from unicorn.geometry.rotations import azim_elev_roll_to_rotation, rotation_angle_between
from unicorn.objectives import NeighborLoss, NeighborMemory, ReconstructionLoss


def rotations(azims) -> torch.Tensor:
    return azim_elev_roll_to_rotation(torch.tensor(azims, dtype=torch.float32), torch.zeros(len(azims)))


def test_bins_edges():
    mem = NeighborMemory(n_bins=5, min_angle=20)
    got = mem.bin_of(torch.tensor([0.0, 19.9, 20.0, 51.9, 52.0, 147.9, 148.0, 180.0, float("nan")]))
    assert got.tolist() == [-1, -1, 0, 0, 1, 3, 4, 4, -1]


def test_search_respects_bins_and_code_distance():
    mem = NeighborMemory(size=64, n_bins=5, min_angle=20)
    azims = [10, 30, 40, 60, 70, 100, 130, 140, 170, 180]  # relative angles to the query at azimuth 0
    codes = torch.arange(len(azims), dtype=torch.float32).unsqueeze(1)
    mem.push(torch.zeros(len(azims), 3, 4, 4), codes, -codes, rotations(azims))
    query_R = rotations([0.0])
    g = torch.Generator().manual_seed(0)
    seen = set()
    for _ in range(60):
        match = mem.search(torch.tensor([[9.0]]), torch.tensor([[0.0]]), query_R, generator=g)
        assert bool(match.valid[0])
        b = int(match.bins[0])
        seen.add(b)
        for index in (match.shape_index, match.texture_index):
            angle = float(rotation_angle_between(mem.R[index], query_R)[0])
            assert 20 + 32 * b - 1e-3 <= angle <= 20 + 32 * (b + 1) + 1e-3
        in_bin = [i for i, a in enumerate(azims) if 20 + 32 * b <= a < 20 + 32 * (b + 1) or (b == 4 and a == 180)]
        # shape query 9 is nearest to the largest code of the bin; texture query 0 (codes -i) to the smallest i
        assert int(match.shape_index[0]) == max(in_bin) and int(match.texture_index[0]) == min(in_bin)
    assert seen == {0, 1, 2, 3, 4}


def test_never_returns_self_even_without_min_angle():
    mem = NeighborMemory(size=16, n_bins=1, min_angle=0)
    R = rotations([0.0, 0.0, 90.0])
    codes = torch.tensor([[0.0], [5.0], [0.1]])
    own = mem.push(torch.zeros(3, 3, 4, 4), codes, codes, R)
    match = mem.search(codes, codes, R, self_index=own)
    assert match.valid.all()
    assert (match.shape_index != own).all() and (match.texture_index != own).all()
    assert match.shape_index.tolist() == [2, 2, 0]


def test_identical_rotations_give_no_nan_and_empty_bins_are_survived():
    mem = NeighborMemory(size=16, n_bins=5, min_angle=20)
    R = azim_elev_roll_to_rotation(torch.tensor([37.0, 37.0]), torch.tensor([13.0, 13.0]), torch.tensor([3.0, 3.0]))
    codes = torch.zeros(2, 2)
    own = mem.push(torch.zeros(2, 3, 4, 4), codes, codes, R)
    match = mem.search(codes, codes, R, self_index=own)  # only same-pose entries: every bin is empty
    assert not match.valid.any() and (match.bins == -1).all()
    # one entry in one bin only: every query draws that bin
    mem.push(torch.ones(1, 3, 4, 4), torch.ones(1, 2), torch.ones(1, 2), R[:1] @ rotations([100.0])[0])
    for seed in range(10):
        match = mem.search(codes, codes, R, self_index=own, generator=torch.Generator().manual_seed(seed))
        assert match.valid.all() and (match.shape_index == 2).all() and (match.bins == 2).all()


def _push(mem, value: float, n: int = 2):
    return mem.push(torch.full((n, 3, 2, 2), value), torch.full((n, 1), value), torch.zeros(n, 1), rotations([0] * n))


def test_ring_keeps_the_newest_entries_in_the_same_tensors_and_checks():
    mem = NeighborMemory(size=4)
    first = _push(mem, 0.0)
    tensors = {name: t.data_ptr() for name, t in mem.state(copy=False).items()}
    assert len(mem) == 2 and first.tolist() == [0, 1] and mem.filled.tolist() == [True, True, False, False]
    for i in (1, 2):
        idx = _push(mem, float(i))
    # the third batch overwrote the oldest rows, the first batch's
    assert len(mem) == 4 and idx.tolist() == [0, 1] and int(mem.head) == 2
    assert mem.images[:, 0, 0, 0].tolist() == [2.0, 2.0, 1.0, 1.0]
    assert {name: t.data_ptr() for name, t in mem.state(copy=False).items()} == tensors  # written in place
    with pytest.raises(ValueError, match="batch of 5 does not fit a memory of 4"):
        mem.push(torch.zeros(5, 3, 2, 2), torch.zeros(5, 1), torch.zeros(5, 1), rotations([0] * 5))
    with pytest.raises(ValueError, match="images"):
        mem.push(torch.zeros(1, 3, 4, 4), torch.zeros(1, 1), torch.zeros(1, 1), rotations([0]))
    with pytest.raises(RuntimeError, match="empty"):
        NeighborMemory().search(torch.zeros(1, 1), torch.zeros(1, 1), rotations([0]))


def test_rows_not_written_yet_are_never_returned():
    mem = NeighborMemory(size=8, n_bins=1, min_angle=0)
    codes = torch.tensor([[3.0], [4.0]])
    mem.push(torch.zeros(2, 3, 2, 2), codes, codes, rotations([90.0, 120.0]))
    # the six empty rows hold zero codes (the nearest to the query) and a zero rotation (in the bin)
    match = mem.search(torch.zeros(1, 1), torch.zeros(1, 1), rotations([0.0]))
    assert match.valid.all() and match.shape_index.tolist() == [0] and match.texture_index.tolist() == [0]


def test_undo_puts_back_what_the_last_push_overwrote():
    mem = NeighborMemory(size=4)
    for i in range(3):
        _push(mem, float(i))
    before = mem.state()
    _push(mem, 9.0)
    mem.undo_push()
    for name, value in before.items():
        assert torch.equal(getattr(mem, name), value), name
    mem.undo_push()  # once only
    assert torch.equal(mem.images, before["images"])
    _push(mem, 9.0)
    mem.forget_push()  # kept: nothing to undo
    mem.undo_push()
    assert mem.images[:, 0, 0, 0].tolist() == [2.0, 2.0, 9.0, 9.0]


def test_saved_states_restore_the_ring_in_place_and_as_entries_in_order():
    mem = NeighborMemory(size=4)
    for i in range(3):
        _push(mem, float(i))
    state = mem.state()
    assert state["images"].data_ptr() != mem.images.data_ptr()  # a copy
    other = NeighborMemory(size=4)
    _push(other, 7.0)
    tensors = other.images.data_ptr()
    other.load_state(state)
    assert other.images.data_ptr() == tensors  # into the tensors it had
    for name, value in state.items():
        assert torch.equal(getattr(other, name), value), name
    # a ring of another size, and the layout without head (entries oldest first): the same entries, in order
    small = NeighborMemory(size=3)
    small.load_state(state)  # the newest 3 of 1, 1, 2, 2
    assert small.images[:, 0, 0, 0].tolist() == [1.0, 2.0, 2.0] and small.filled.all() and int(small.head) == 0
    fifo = {name: state[name][[2, 3, 0, 1]] for name in NeighborMemory._FIELDS}  # oldest first, no head
    large = NeighborMemory(size=6)
    large.load_state(fifo)
    assert large.images[:, 0, 0, 0].tolist() == [1.0, 1.0, 2.0, 2.0, 0.0, 0.0] and len(large) == 4
    assert int(_push(large, 5.0)[0]) == 4  # the next push after the newest entry
    large.load_state({name: None for name in state})
    assert len(large) == 0 and large.R is None


def test_the_memory_follows_its_loss_to_another_device_in_float32():
    mem = NeighborMemory(size=4)
    loss = NeighborLoss(ReconstructionLoss(), mem, weight=1.0)
    loss.to("cpu")  # nothing pushed yet: nothing to move
    assert mem.R is None
    _push(mem, 1.0)
    tensors = {name: t.data_ptr() for name, t in mem.state(copy=False).items()}
    loss.to("cpu")  # already there: the same tensors (a compiled step's graphs keep them)
    assert {name: t.data_ptr() for name, t in mem.state(copy=False).items()} == tensors
    loss.to("meta")  # moved with the module, not at the next push inside a step
    assert {t.device.type for t in mem.state(copy=False).values()} == {"meta"}
    loss.half()  # the module's dtype: the memory stays float32 (the same state in checkpoints)
    assert mem.images.dtype == mem.R.dtype == torch.float32
