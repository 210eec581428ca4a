"""Shared test options: CPU by default, CUDA tests marked ``gpu`` run only where a GPU is present."""

import os

import pytest
import torch

#: fixtures shared by several test packages (datasets in real on-disk formats, the synthetic set, a cache)
pytest_plugins = ["tests.support.fixtures"]


def _test_threads() -> int:
    """torch's threads per test process: ``UNICORN_TEST_THREADS``, else the cores shared out among pytest-xdist's
    workers (at most 2 each), so that parallel workers do not oversubscribe the machine."""
    if "UNICORN_TEST_THREADS" in os.environ:
        return int(os.environ["UNICORN_TEST_THREADS"])
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    return max(1, min(2, (os.cpu_count() or 1) // workers))


# torch gives some warnings once per process; every time here, so that pytest's filters (pyproject.toml) see each
# one where it happens, not only the first in a worker
torch.set_warn_always(True)

# a 2-thread torch job beside another busy process waits at its thread barriers: never ask for more than our share
torch.set_num_threads(_test_threads())
if "PYTEST_XDIST_WORKER" in os.environ:  # and the same share for the subprocesses a test starts
    os.environ.setdefault("OMP_NUM_THREADS", str(torch.get_num_threads()))


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
