"""The training callbacks' outputs."""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from unicorn.lit.callbacks import overview_labels, save_overview


def test_the_training_pictures_name_their_columns_and_keep_their_cells(tmp_path) -> None:
    size, labels = 32, overview_labels(4, background=True)
    assert labels == ["input", "recon.", "az 30", "az 120", "az 210", "az 300", "texture", "backgr."]
    cells = torch.rand(2, len(labels), 3, size, size)  # (rows, columns, 3, S, S)
    grid = cells.permute(2, 0, 3, 1, 4).reshape(3, 2 * size, len(labels) * size)  # as render_overview lays them
    save_overview(grid, size, labels, tmp_path / "step.png")
    image = np.asarray(Image.open(tmp_path / "step.png"))
    head, pad, side = 24, 2, 64  # 32-pixel cells shown at 64
    assert image.shape == (head + 2 * (side + pad) + pad, len(labels) * (side + pad) + pad, 3)
    for c in range(len(labels)):
        x = pad + c * (side + pad)
        assert (image[:head, x : x + side] < 128).any(), f"no header over column {c}"
        for r in range(2):
            y = head + pad + r * (side + pad)
            expected = (cells[r, c].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(image[y : y + side : 2, x : x + side : 2], expected)
