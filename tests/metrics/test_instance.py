"""Instance-level metrics against independent computations (numpy, naive loops)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from unicorn.metrics import (
    active_units,
    code_spread,
    color_errors,
    flip_rate,
    mean_foreground_color,
    rotation_accuracy,
    win_share,
)


def test_mean_foreground_color_matches_a_pixel_loop() -> None:
    g = torch.Generator().manual_seed(0)
    images = torch.rand(4, 3, 7, 9, generator=g)
    masks = torch.rand(4, 1, 7, 9, generator=g)
    masks[2] = 0.1  # nothing above the threshold: NaN
    got = mean_foreground_color(images, masks)
    for b in range(4):
        picked = [images[b, :, i, j].numpy() for i in range(7) for j in range(9) if masks[b, 0, i, j] >= 0.5]
        if not picked:
            assert torch.isnan(got[b]).all()
            continue
        np.testing.assert_allclose(got[b].numpy(), np.mean(picked, axis=0), rtol=1e-5, atol=1e-6)
    # (B, H, W) bool masks work the same
    torch.testing.assert_close(mean_foreground_color(images, masks[:, 0] >= 0.5), got, equal_nan=True)
    with pytest.raises(ValueError, match=r"^masks must have shape \(4, 7, 9\) or \(4, 1, 7, 9\), got \(4, 1, 3, 9\)$"):
        mean_foreground_color(images, masks[:, :, :3])


@pytest.mark.parametrize("r", [1, 2])
def test_mean_foreground_color_interior_matches_a_pixel_loop(r: int) -> None:
    g = torch.Generator().manual_seed(1)
    images = torch.rand(3, 3, 9, 11, generator=g)
    masks = torch.zeros(3, 9, 11)
    masks[0, 1:8, 2:10] = 1.0  # a block: its eroded interior
    masks[0, 3, 5] = 0.0  # a hole erodes its neighbours too
    masks[1, :, :6] = 1.0  # touching the frame: the frame is not a border
    masks[2, 4, 3:8] = 1.0  # a one-pixel line: nothing survives, the whole mask is kept
    got = mean_foreground_color(images, masks, interior=r)
    H, W = masks.shape[1:]

    def inside(b: int, i: int, j: int) -> bool:
        ys = range(max(i - r, 0), min(i + r + 1, H))
        xs = range(max(j - r, 0), min(j + r + 1, W))
        return all(masks[b, y, x] >= 0.5 for y in ys for x in xs)

    for b in range(3):
        kept = [(i, j) for i in range(H) for j in range(W) if inside(b, i, j)]
        if not kept:
            kept = [(i, j) for i in range(H) for j in range(W) if masks[b, i, j] >= 0.5]
        expected = np.mean([images[b, :, i, j].numpy() for i, j in kept], axis=0)
        np.testing.assert_allclose(got[b].numpy(), expected, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(got[1], mean_foreground_color(images, masks)[1])  # the test can tell
    with pytest.raises(ValueError, match="interior"):
        mean_foreground_color(images, masks, interior=-1)


def test_color_errors_against_numpy() -> None:
    rng = np.random.default_rng(1)
    gt = rng.uniform(size=(6, 3))
    pred = rng.uniform(size=(6, 3))
    gt[4] = np.nan  # an image without a foreground: left out of the mean colour, NaN errors
    model, base = color_errors(torch.tensor(pred), torch.tensor(gt))
    mean = np.nanmean(gt, axis=0)
    for i in range(6):
        want_model = sum(abs(pred[i, c] - gt[i, c]) for c in range(3)) / 3
        want_base = sum(abs(mean[c] - gt[i, c]) for c in range(3)) / 3
        if i == 4:
            assert math.isnan(model[i]) and math.isnan(base[i])
        else:
            assert model[i].item() == pytest.approx(want_model) and base[i].item() == pytest.approx(want_base)
    # predicting each image's own colour beats the constant; predicting the mean ties with it
    model, base = color_errors(torch.tensor(np.tile(mean, (6, 1))), torch.tensor(gt))
    torch.testing.assert_close(model, base, equal_nan=True)
    fixed = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    _, base = color_errors(torch.tensor(pred), torch.tensor(gt), reference=fixed)
    assert base[0].item() == pytest.approx(np.abs(gt[0] - 0.5).mean())
    with pytest.raises(ValueError, match="no image"):
        color_errors(torch.zeros(2, 3), torch.full((2, 3), math.nan))


def test_win_share_counts_wins_and_half_ties() -> None:
    rng = np.random.default_rng(2)
    a, b = rng.integers(0, 4, 50).astype(float), rng.integers(0, 4, 50).astype(float)
    a[3] = np.nan
    wins = 0.0
    n = 0
    for x, y in zip(a, b):
        if np.isnan(x) or np.isnan(y):
            continue
        n += 1
        wins += 1.0 if x < y else 0.5 if x == y else 0.0
    assert win_share(torch.tensor(a), torch.tensor(b)) == pytest.approx(wins / n)
    assert math.isnan(win_share(torch.tensor([math.nan]), torch.tensor([1.0])))
    with pytest.raises(ValueError, match="shape"):
        win_share(torch.zeros(3), torch.zeros(2))


def test_rotation_accuracy_and_flip_rate() -> None:
    errors = np.random.default_rng(3).uniform(0, 180, 200)
    t = torch.tensor(errors)
    assert rotation_accuracy(t) == pytest.approx(sum(e < 30 for e in errors) / 200)
    assert flip_rate(t) == pytest.approx(sum(e > 150 for e in errors) / 200)
    assert flip_rate(t, 90.0) == pytest.approx(sum(e > 90 for e in errors) / 200)
    with pytest.raises(ValueError, match="non-empty"):
        flip_rate(torch.zeros(0))


def test_code_spread_and_active_units_against_numpy() -> None:
    rng = np.random.default_rng(4)
    codes = rng.normal(size=(16, 5))
    codes[:, 2] = 0.7  # a dimension that ignores the image
    spread = code_spread(torch.tensor(codes))
    np.testing.assert_allclose(spread.numpy(), np.std(codes, axis=0), rtol=1e-10, atol=1e-12)
    assert spread[2] == 0
    assert code_spread(torch.tensor(codes), active_dims=2).shape == (2,)
    assert code_spread(torch.tensor(codes), active_dims=0).shape == (0,)  # a fully masked code
    with pytest.raises(ValueError, match="active_dims"):
        code_spread(torch.tensor(codes), active_dims=6)

    acts = np.maximum(rng.normal(size=(8, 6)), 0)
    acts[:, 1] = 0.0  # a dead unit
    alive = active_units(torch.tensor(acts))
    assert alive.tolist() == [any(acts[b, u] > 0 for b in range(8)) for u in range(6)]
    assert not alive[1]
