"""Interactive 3D views of meshes in the HTML reports, working offline from the report's folder.

The viewer is Google's ``<model-viewer>`` web component (npm ``@google/model-viewer``, its self-contained UMD
build, which bundles three.js), vendored in ``unicorn/evaluation/assets`` with its licences
(``THIRD_PARTY_LICENSES.txt``). :func:`install_viewer` copies both into the report folder (``_viewer/``: no
output name of ``unicorn-reconstruct`` starts with ``_``), so the page needs
neither a network nor a server. The meshes are embedded in the page as ``data:`` URLs of their GLB bytes:
browsers refuse to ``fetch`` a ``file://`` URL, which a page opened from disk would otherwise need.
"""

from __future__ import annotations

import base64
import html
import os
import shutil
from pathlib import Path

__all__ = ["VIEWER_ASSETS", "VIEWER_FILES", "VIEWER_SCRIPT", "install_viewer", "viewer_element", "viewer_script_tags"]

VIEWER_ASSETS = Path(__file__).resolve().parent / "assets"
VIEWER_SCRIPT = "model-viewer-umd.min.js"
_LICENSES = "THIRD_PARTY_LICENSES.txt"
#: the files :func:`install_viewer` copies
VIEWER_FILES = (VIEWER_SCRIPT, _LICENSES)

#: marks each viewer with data-state="loaded" or "error" once model-viewer has tried its mesh, and says so
_STATE_SCRIPT = """<script>
document.querySelectorAll("model-viewer").forEach(function (v) {
  function mark(state, text) {
    v.dataset.state = state;
    var status = v.querySelector(".mv-status");
    if (status) status.textContent = text;
  }
  v.addEventListener("load", function () { mark("loaded", ""); });
  v.addEventListener("error", function () { mark("error", "could not show this mesh"); });
  if (v.loaded) mark("loaded", "");
});
</script>"""


def install_viewer(folder: str | os.PathLike, subdir: str = "_viewer") -> str:
    """Copy the viewer script and its licences to ``folder/subdir``; returns the script's relative URL."""
    target = Path(folder) / subdir
    target.mkdir(parents=True, exist_ok=True)
    for name in VIEWER_FILES:
        source, copy = VIEWER_ASSETS / name, target / name
        if not copy.is_file() or copy.stat().st_size != source.stat().st_size:
            shutil.copyfile(source, copy)
    return f"{subdir}/{VIEWER_SCRIPT}"


def viewer_script_tags(script_url: str) -> tuple[str, str]:
    """``(head, end_of_body)`` HTML: the viewer's script tag and the load-state script."""
    return f'<script src="{html.escape(script_url)}"></script>', _STATE_SCRIPT


def viewer_element(
    glb: bytes | str | os.PathLike, size: int, alt: str = "3D mesh", orbit: tuple[float, float] | None = None
) -> str:
    """A ``<model-viewer>`` element showing a GLB (its bytes or its file), rotate by dragging, zoom by scrolling.

    Args:
        glb: the GLB bytes, or the path of a ``.glb`` file (embedded either way).
        size: side of the square view in CSS pixels.
        alt: accessible description.
        orbit: the initial camera's azimuth and elevation in degrees (:func:`look_at_view_transform`'s,
            which model-viewer's ``camera-orbit`` shares: theta = azimuth, phi = 90 - elevation); default:
            model-viewer's front view.
    """
    data = glb if isinstance(glb, bytes) else Path(glb).read_bytes()
    url = "data:model/gltf-binary;base64," + base64.b64encode(data).decode("ascii")
    camera = f'camera-orbit="{orbit[0]:.2f}deg {90.0 - orbit[1]:.2f}deg auto" ' if orbit is not None else ""
    return (
        # eager: reports put viewers below the fold, and model-viewer's default waits until they are scrolled to
        f'<model-viewer src="{url}" alt="{html.escape(alt)}" {camera}loading="eager" camera-controls '
        'touch-action="pan-y" '
        f'interaction-prompt="none" shadow-intensity="0" exposure="1" environment-image="neutral" '
        f'style="width:{size}px;height:{size}px;background:#f4f4f4">'
        f'<div class="mv-status" slot="poster" style="font-size:.8em;color:#888;padding:.5em">loading 3D view…</div>'
        f"</model-viewer>"
    )
