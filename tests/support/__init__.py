"""Helpers shared by the tests (fixture files in real on-disk formats, tiny models and runs, payloads).

Tests import shared code from here, never from each other; pytest fixtures used by several test packages
are in :mod:`tests.support.fixtures` (registered by ``tests/conftest.py``)."""
