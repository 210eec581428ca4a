"""unicorn.model stays below unicorn.io; the names README.md documents as ``unicorn.model.*`` still resolve."""

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
def test_readme_names_are_the_io_functions(name: str) -> None:
    import unicorn.io
    import unicorn.model

    assert getattr(unicorn.model, name) is getattr(unicorn.io, name)
    with pytest.raises(AttributeError):
        unicorn.model.textured_mesh  # noqa: B018  (not documented as unicorn.model.*: moved without a re-export)
