"""Shared fixtures for the model tests."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import IMAGE_SIZE, tiny_config
from unicorn.model import Unicorn


@pytest.fixture
def tiny_model() -> Unicorn:
    torch.manual_seed(0)
    return Unicorn(tiny_config())


@pytest.fixture
def images() -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    return torch.rand(3, 3, IMAGE_SIZE, IMAGE_SIZE, generator=g)
