"""Tiny checkpoints, fixture datasets and input images for the evaluation and reconstruction tests."""

from __future__ import annotations

from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import torch
from PIL import Image

from tests.support.prepared import IMAGE_SIZE, generated
from unicorn.config import model_preset
from unicorn.evaluation import EvaluationResult, Sample
from unicorn.io import save_model
from unicorn.model import Unicorn

TEXTURE_SIZE = 16


def tiny_model(family: str = "real", seed: int = 0) -> Unicorn:
    """An untrained model at 32 px with 16 px textures and no perceptual loss (fast on CPU)."""
    torch.manual_seed(seed)
    cfg = model_preset(family, image_size=IMAGE_SIZE, texture={"size": TEXTURE_SIZE}, loss={"perceptual": None})
    return Unicorn(cfg).eval()


def tiny_checkpoint(path: Path, family: str = "real", **info) -> Path:
    """Write :func:`tiny_model` as a plain checkpoint."""
    return save_model(tiny_model(family), path, **info)


def synthetic_data(out: Path) -> Path:
    """Synthetic NMR set: 2 categories x 3 models x 2 views at 32 px (train split: 2 models per category)."""
    return generated("eval-nmr", out)


def write_inputs(folder: Path) -> dict[str, Path]:
    """A transparent PNG cut-out (object off-centre) and an opaque landscape JPEG."""
    folder.mkdir(parents=True, exist_ok=True)
    rgba = np.zeros((60, 90, 4), dtype=np.uint8)
    rgba[8:30, 50:84] = (200, 60, 40, 255)  # object in the top-right corner
    Image.fromarray(rgba, "RGBA").save(folder / "cutout.png")
    rng = np.random.default_rng(0)
    photo = (rng.random((40, 70, 3)) * 255).astype(np.uint8)
    Image.fromarray(photo).save(folder / "photo.jpg")
    return {"cutout": folder / "cutout.png", "photo": folder / "photo.jpg"}


class _Sources(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.sources: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for key, value in attrs:
            if (tag, key) in (("img", "src"), ("a", "href")) and value:
                self.sources.append(unquote(value))


def referenced_files(page: Path) -> list[str]:
    """Every ``img src`` and ``a href`` of an HTML file, as the paths they name (percent-decoded)."""
    parser = _Sources()
    parser.feed(page.read_text(encoding="utf-8"))
    return parser.sources


def report_result(model, n_samples: int = 2) -> EvaluationResult:
    """A small hand-made evaluation result on random images: two samples, per-image rows and a table."""
    x = torch.rand(n_samples, 3, 32, 32)
    with torch.no_grad():
        pred = model.predict(x)
        rec, alpha = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
    samples = [
        Sample(i, "chair", x[i], rec[i], alpha[i], (alpha[i] > 0.2).float(), pred.verts[i], pred.texture[i],
               pred.R[i], pred.T[i], {"mask-iou": 0.5, "rec-mse": 0.01})
        for i in range(n_samples)
    ]  # fmt: skip
    per_image = [{"index": 0, "group": "chair", "mask-iou": 0.5, "rec-mse": 0.01},
                 {"index": 1, "group": "chair", "mask-iou": float("nan"), "rec-mse": 0.03}]  # fmt: skip
    table = [
        {"group": "chair", "n-images": 2, "mask-iou": 0.5, "rec-mse": 0.02},
        {"group": "mean", "n-images": 2, "mask-iou": 0.5, "rec-mse": 0.02},
    ]
    return EvaluationResult("shapenet", per_image, table, ["mask-iou", "rec-mse"], samples, 1.5)
