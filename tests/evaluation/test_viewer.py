"""The interactive 3D views of the HTML reports load their meshes in a real browser (headless Chromium), offline.

Chromium opens the reports from disk (``file://``, no server, no network): the vendored ``<model-viewer>`` must
load from the report folder, every embedded GLB must load (``data-state="loaded"``), and a screenshot of a view
must show the mesh, not an empty canvas.
"""

from __future__ import annotations

import io
import re
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.support.chromium import EXECUTABLE, Chromium
from tests.support.evaluation import report_result, tiny_checkpoint, tiny_model, write_inputs
from unicorn.cli.reconstruct import main as reconstruct_main
from unicorn.evaluation import write_report
from unicorn.evaluation.viewer import VIEWER_SCRIPT

pytestmark = pytest.mark.skipif(
    EXECUTABLE is None, reason="headless Chromium is not installed (Debian: apt-get install chromium; .ci/run does)"
)
STATES = "Array.from(document.querySelectorAll('model-viewer')).map(v => v.dataset.state || '')"


def _drawn_fraction(png: bytes) -> float:
    """Fraction of the pixels of a viewer's screenshot that differ from its flat background."""
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)
    ring = np.concatenate([pixels[:, :3].reshape(-1, 3), pixels[:, -3:].reshape(-1, 3)])  # left and right edges
    background = np.median(ring, axis=0)  # the mesh is framed in the middle
    return float((np.abs(pixels - background).max(axis=-1) > 24).mean())


def check_viewers(page: Path, count: int) -> None:
    """All ``count`` viewers of ``page`` load their mesh, and the first one draws it; without it, nothing is drawn."""
    with Chromium(page.resolve().as_uri()) as browser:
        states = browser.wait_for(f"{STATES}.every(s => s) && {STATES}") or browser.evaluate(STATES)
        assert states == ["loaded"] * count
        assert browser.evaluate("customElements.get('model-viewer') !== undefined")
        # 'load' can come before the first frame is drawn: shoot until the mesh shows, for up to 30 s
        for _ in range(60):
            drawn = _drawn_fraction(browser.screenshot("model-viewer"))
            if drawn > 0.2:
                break
            time.sleep(0.5)
    # the same element without its mesh draws nothing: the check above can fail
    text = page.read_text(encoding="utf-8")
    empty_page = page.with_name("empty_viewer.html")
    empty_page.write_text(re.sub(r'src="data:[^"]*"', 'src=""', text), encoding="utf-8")
    with Chromium(empty_page.resolve().as_uri()) as browser:
        browser.wait_for("customElements.get('model-viewer') !== undefined")
        time_for_nothing = browser.wait_for("false", timeout=3.0)
        assert not time_for_nothing
        empty = _drawn_fraction(browser.screenshot("model-viewer"))
    assert drawn > 0.2 and empty < 0.05, (drawn, empty)


def test_reconstruct_index_shows_each_mesh_in_3d(tmp_path):
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt", "real")
    write_inputs(tmp_path / "inputs")
    out = tmp_path / "out"
    args = [str(checkpoint), str(tmp_path / "inputs"), "--out", str(out), "--view-size", "48", "--quiet"]
    assert reconstruct_main([*args, "--turntable-frames", "0", "--strip-views", "2", "--device", "cpu"]) == 0
    assert (out / "_viewer" / VIEWER_SCRIPT).is_file() and (out / "_viewer" / "THIRD_PARTY_LICENSES.txt").is_file()
    check_viewers(out / "index.html", 2)


def test_eval_report_shows_each_sample_in_3d(tmp_path):
    model = tiny_model("real")
    torch.manual_seed(0)
    paths = write_report(model, report_result(model), tmp_path / "report", "test", {}, view_size=32, turntable_frames=0)
    check_viewers(paths["html"], 2)
