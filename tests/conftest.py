"""Shared test options: CPU by default, CUDA tests marked ``gpu`` run only where a GPU is present."""

import os

import pytest
import torch

#: fixtures shared by several test packages (datasets in real on-disk formats, the synthetic set, a cache)
pytest_plugins = ["tests.support.fixtures"]

# two cores on the CI machine: keep torch from oversubscribing them
torch.set_num_threads(int(os.environ.get("UNICORN_TEST_THREADS", "2")))


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip_gpu = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield
