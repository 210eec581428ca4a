"""unicorn.model stays below unicorn.io and holds no alias of its file functions."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_model_does_not_import_io_or_lightning() -> None:
    code = (
        "import sys, unicorn.model; print(sorted(m for m in sys.modules if m.startswith(('unicorn.io', 'lightning'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("name", ["load_reference_checkpoint", "export_prediction", "save_mesh"])
def test_file_functions_are_io_names_only(name: str) -> None:
    import unicorn.io
    import unicorn.model

    assert callable(getattr(unicorn.io, name))
    assert not hasattr(unicorn.model, name)  # files in and out are unicorn.io's: no alias on the model floor
