"""Shared fixtures for the objectives' tests."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import IMAGE_SIZE


@pytest.fixture
def images() -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    return torch.rand(3, 3, IMAGE_SIZE, IMAGE_SIZE, generator=g)
