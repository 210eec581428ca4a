"""Unit tests of the training pieces that need no training run."""

from __future__ import annotations

import pytest
import torch

from unicorn.hostsync import sync_free
from unicorn.lit import StageCallback, StreamBatchSampler


def test_stream_is_deterministic_resumable_and_sharded():
    full = StreamBatchSampler(10, 4, seed=3)
    it = iter(full)
    batches = [next(it) for _ in range(6)]  # crosses several permutations of the 10 items
    resumed = iter(StreamBatchSampler(10, 4, seed=3, start_batch=4))
    assert [next(resumed) for _ in range(2)] == batches[4:]
    positions = [p for batch in batches for p, _ in batch]
    assert positions == list(range(24))
    # the first 10 positions visit every item once, and index_at agrees with the stream
    first_epoch = [index for batch in batches for p, index in batch if p < 10]
    assert sorted(first_epoch) == list(range(10))
    assert [full.index_at(p) for p in range(24)] == [index for batch in batches for _, index in batch]
    r0 = next(iter(StreamBatchSampler(10, 2, seed=3, rank=0, world_size=2)))
    r1 = next(iter(StreamBatchSampler(10, 2, seed=3, rank=1, world_size=2)))
    assert [p for p, _ in r0] == [0, 1] and [p for p, _ in r1] == [2, 3]
    assert StreamBatchSampler(10, 4, seed=4).batch_at(0) != batches[0]


def test_stage_schedule():
    cb = StageCallback(
        dims={"shape": [0, 2, 8, 32], "texture": [2, 8, 32, 128], "background": [4, 8, 32, 128]},
        milestones=[100, 200, 300],
        curriculum={"translation": 10, "deformation": 20, "scale": 50, "elevation_roll": 30},
        texture_averaging={"constant_stages": 0, "p": 0.2, "random_until_stage": 4},
    )
    assert [cb.fixed_stage(s) for s in (0, 99, 100, 199, 200, 300, 10**6)] == [1, 1, 2, 2, 3, 4, 4]
    s0, s1 = cb.state_at(0, 1), cb.state_at(20, 1)
    assert s0["switches"] == {"translation": False, "deformation": False, "scale": False, "elevation_roll": False}
    assert s1["switches"] == {"translation": True, "deformation": True, "scale": False, "elevation_roll": False}
    assert cb.state_at(30, 1)["switches"]["elevation_roll"] and not cb.state_at(30, 1)["switches"]["scale"]
    assert s0["dims"] == {"shape": 0, "texture": 2, "background": 4} and s0["texture_p"] == 0.2
    assert cb.state_at(300, 4)["texture_p"] == 0.0 and cb.state_at(300, 4)["dims"]["texture"] == 128
    lines = cb._describe(cb.state_at(99, 1), cb.state_at(100, 2), 100)
    assert lines == ["iteration 100: stage 1 -> stage 2 (code sizes: shape 2, texture 8, background 8)"]
    with pytest.raises(ValueError, match="increasing"):
        StageCallback(dims={}, milestones=[3, 2, 1])


def test_constant_textures_end_at_an_iteration_when_told():
    # the reference's table ends them an epoch before stage 2 (constant_txt 10 epochs, stage 2 at 11)
    ta = {"constant_stages": 1, "constant_until": 90, "p": 0.2, "random_until_stage": 4}
    cb = StageCallback(dims={"texture": [2, 8, 32, 128]}, milestones=[100, 200, 300], texture_averaging=ta)
    assert [cb.state_at(s, cb.fixed_stage(s))["texture_p"] for s in (0, 89, 90, 99, 100, 300)] == [
        1.0,
        1.0,
        0.2,
        0.2,
        0.2,
        0.0,
    ]
    assert cb.state_at(50, 2)["texture_p"] == 1.0  # an early stage change (plateau mode) does not end them
    by_stage = StageCallback(
        dims={"texture": [2, 8, 32, 128]}, milestones=[100, 200, 300], texture_averaging=ta | {"constant_until": None}
    )
    assert [by_stage.state_at(s, by_stage.fixed_stage(s))["texture_p"] for s in (90, 99, 100)] == [1.0, 1.0, 0.2]


def test_plateau_detection():
    cb = StageCallback(
        dims={"shape": [0, 2, 8, 32], "texture": [2, 8, 32, 128]},
        milestones=[1, 2, 3],
        mode="plateau",
        plateau={"window": 4, "check_every": 1, "threshold": 0.05, "patience": 2, "min_steps": 10},
    )
    cb._history.extend([1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3])  # still improving
    assert not cb._plateau_reached(stage=1, step=20)
    cb._history.extend([0.3] * 8)  # flat
    assert not cb._plateau_reached(stage=1, step=5)  # stage too short
    assert not cb._plateau_reached(stage=1, step=21)  # first strike
    assert cb._plateau_reached(stage=1, step=22)  # patience reached
    assert not cb._plateau_reached(stage=4, step=23)  # no stage after the last
    restored = StageCallback(dims={"texture": [1, 2, 3, 4]}, milestones=[1, 2, 3], mode="plateau")
    restored.load_state_dict(cb.state_dict())
    assert list(restored._history) == list(cb._history) and restored._strikes == cb._strikes


def test_texture_averaging_draws():
    from unicorn.config import model_preset
    from unicorn.lit import UnicornLitModule

    cfg = model_preset("shapenet", image_size=32, loss={"perceptual": None}, template={"level": 1})
    module = UnicornLitModule(cfg, seed=5)
    module.texture_average_p.fill_(0.2)
    draws = [module.average_texture(step) for step in range(2000)]
    assert draws == [module.average_texture(step) for step in range(2000)]  # a pure function of the step
    assert 0.17 < sum(draws) / len(draws) < 0.23
    for p in (0.2, 0.5, 0.3333333333):  # each the draw of a generator seeded by the iteration, in float32
        module.texture_average_p.fill_(p)
        for step in [*range(250, 270), 1999]:
            g = torch.Generator().manual_seed(5 * 1_000_003 + step)
            assert module.average_texture(step) == bool(torch.rand((), generator=g) < p), (p, step)
    module.texture_average_host = 0.0  # the stage callback's copy, read by the steps without host reads
    with sync_free():
        assert not any(module.average_texture(s) for s in range(10))
    module.texture_average_p.fill_(1.0)
    assert all(module.average_texture(s) for s in range(10))
    assert [module.phase(s) for s in range(4)] == ["pose", "3d", "pose", "3d"]
    module.alternation_period = 2
    assert [module.phase(s) for s in range(6)] == ["pose", "pose", "3d", "3d", "pose", "pose"]
