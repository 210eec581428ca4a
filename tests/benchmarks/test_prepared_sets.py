"""The fixtures' synthetic sets written beforehand (``python -m tests.support.prepared``, the GPU kit's test data):
a copy is used only where this checkout's generator would write the same."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.support.prepared import ENV, SETS, generated
from unicorn.data.synthetic.writer import StaleSyntheticDataset


@pytest.fixture
def prepared(tmp_path: Path, synthetic_cache: Path, synth_nmr: Path, monkeypatch) -> Path:
    """A ``$UNICORN_TEST_DATA`` holding the ``cache`` and ``nmr`` sets (copies of the session's)."""
    folder = tmp_path / "prepared"
    shutil.copytree(synthetic_cache, folder / "cache")
    shutil.copytree(synth_nmr, folder / "nmr")
    monkeypatch.setenv(ENV, str(folder))
    return folder


def test_a_prepared_set_is_copied(tmp_path: Path, prepared: Path) -> None:
    for name in ("cache", "nmr"):
        out = generated(name, tmp_path / name)
        copied = sorted(p.relative_to(out) for p in out.rglob("*"))
        assert copied == sorted(p.relative_to(prepared / name) for p in (prepared / name).rglob("*"))
        assert (SETS[name].dataset(out) / "synthetic.json").is_file()


@pytest.mark.parametrize(
    ("name", "change", "named"),
    [
        ("nmr", {"generator_version": 1}, "generator_version=1"),
        ("nmr", {"n_views": 24}, "n_views=24"),
        ("cache", {"image_size": 64}, "image_size=64"),
    ],
    ids=["older-generator", "other-views", "cache-other-size"],
)
def test_a_prepared_set_of_another_generator_or_settings_is_refused(
    tmp_path: Path, prepared: Path, name: str, change: dict, named: str
) -> None:
    manifest = SETS[name].dataset(prepared / name) / "synthetic.json"
    manifest.write_text(json.dumps({**json.loads(manifest.read_text()), **change}))
    with pytest.raises(StaleSyntheticDataset, match=rf"{prepared / name} is not this checkout's set \(.*{named}"):
        generated(name, tmp_path / name)


def test_a_prepared_cache_without_the_set_is_refused(tmp_path: Path, prepared: Path) -> None:
    shutil.rmtree(SETS["cache"].dataset(prepared / "cache"))
    with pytest.raises(StaleSyntheticDataset, match="no synthetic.json in"):
        generated("cache", tmp_path / "cache")
