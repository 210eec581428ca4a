"""Shared shapes for the metric tests."""

from __future__ import annotations

import pytest
import torch
import trimesh


def _asymmetric_blob() -> tuple[torch.Tensor, torch.Tensor]:
    """A closed, asymmetric shape (no rotational or mirror symmetry), about 0.9 wide."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    v = torch.tensor(mesh.vertices, dtype=torch.float32)
    bump = torch.exp(-((v - torch.tensor([0.6, 0.6, 0.5])) ** 2).sum(-1, keepdim=True) / 0.1)
    v = v * torch.tensor([0.45, 0.3, 0.2]) + 0.08 * bump * v + 0.05 * torch.relu(v[:, :1]) * v
    return v, torch.tensor(mesh.faces, dtype=torch.long)


@pytest.fixture(scope="session")
def blob() -> tuple[torch.Tensor, torch.Tensor]:
    return _asymmetric_blob()
