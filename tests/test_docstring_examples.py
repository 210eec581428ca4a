"""The examples in the package's docstrings (``>>>``) run as written and print what they show."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
MODULES = sorted(
    ".".join(path.relative_to(SRC).with_suffix("").parts)
    for path in (SRC / "unicorn").rglob("*.py")
    if ">>>" in path.read_text(encoding="utf-8")
)


def test_the_package_has_examples():
    assert len(MODULES) >= 10  # the search found the package's files


@pytest.mark.parametrize("module", MODULES)
def test_docstring_examples_run_as_written(module):
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    report: list[str] = []
    examples = [test for test in doctest.DocTestFinder().find(importlib.import_module(module)) if test.examples]
    assert examples, f"{module} names >>> outside a docstring"
    for test in examples:
        runner.run(test, out=report.append)
    assert runner.failures == 0, "".join(report)
