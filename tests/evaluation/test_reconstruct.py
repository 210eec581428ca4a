"""Reconstruction helpers: output names and pose records (the command itself is tested in tests/cli)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from unicorn.evaluation.reconstruct import pose_record, unique_names
from unicorn.geometry.rotations import azim_elev_roll_to_rotation

from .helpers import IMAGE_SIZE


def test_unique_names() -> None:
    assert unique_names([Path("/x/a/0000.png"), Path("/x/b/0000.png"), Path("/x/b/1.jpg")]) == [
        "a_0000",
        "b_0000",
        "b_1",
    ]
    assert unique_names([Path("/x/cat dog.png"), Path("/y/b.png")]) == ["cat_dog", "b"]
    assert unique_names([Path("/x/a.png"), Path("/x/a.jpg")]) == ["a", "a_1"]


def test_pose_record(real_model) -> None:
    with torch.no_grad():
        pred = real_model.predict(torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE))
    record = json.loads(json.dumps(pose_record(real_model, pred, 1)))  # JSON-ready
    torch.testing.assert_close(torch.tensor(record["R"]), pred.R[1])
    rebuilt = azim_elev_roll_to_rotation(
        torch.tensor(record["azimuth"]), torch.tensor(record["elevation"]), torch.tensor(record["roll"])
    )
    torch.testing.assert_close(rebuilt.reshape(3, 3), pred.R[1], atol=1e-5, rtol=0)
    assert abs(sum(record["candidate_probabilities"]) - 1) < 1e-5 and record["camera"]["fov_degrees"] > 0
