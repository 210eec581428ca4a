"""Neighbour memory: bins, self-exclusion, empty bins, FIFO."""

from __future__ import annotations

import pytest
import torch

from unicorn.geometry.rotations import azim_elev_roll_to_rotation, rotation_angle_between
from unicorn.objectives import NeighborMemory


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


def test_fifo_capacity_and_checks():
    mem = NeighborMemory(size=4)
    for i in range(3):
        idx = mem.push(torch.full((2, 3, 2, 2), float(i)), torch.zeros(2, 1), torch.zeros(2, 1), rotations([0, 0]))
    assert len(mem) == 4 and idx.tolist() == [2, 3]
    assert mem.images[:, 0, 0, 0].tolist() == [1.0, 1.0, 2.0, 2.0]
    with pytest.raises(ValueError):
        mem.push(torch.zeros(5, 3, 2, 2), torch.zeros(5, 1), torch.zeros(5, 1), rotations([0] * 5))
    state = mem.state()
    other = NeighborMemory(size=4)
    other.load_state(state)
    assert len(other) == 4
    with pytest.raises(RuntimeError, match="empty"):
        NeighborMemory().search(torch.zeros(1, 1), torch.zeros(1, 1), rotations([0]))
