"""Shared loader for datasets annotated CMR-style: one record per object with a box, a mask and keypoints.

CUB-200-2011 (:mod:`unicorn.data.cub`) and Pascal3D+ Car (:mod:`unicorn.data.p3d`) both store a MATLAB struct
array ``images`` whose records have ``rel_path``, ``bbox`` (struct ``x1, y1, x2, y2``, 1-based), ``parts``
(3, K) (x, y, visible; 1-based) and ``mask`` (H, W). Each item is the square crop around the padded (and, for
training, jittered) box, with the image border replicated where the crop leaves the image and the mask zero
there, resized to ``img_size``; training items are flipped horizontally with probability 0.5, keypoints
mirrored and their left/right names swapped.

Images are read as stored, EXIF orientation NOT applied (unlike the other loaders): the boxes, masks and keypoints
were made on the stored pixel grid (MATLAB's ``imread``, which ignores the tag, as does the reference's PIL
loading), so turning the image upright would move it away from its annotations. CUB's and Pascal3D+'s JPEGs carry
no orientation tag in practice, so the two readings agree on them anyway.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from unicorn.data.common import OnError, UnicornDataset, dummy_pose, item_rng
from unicorn.data.framing import (
    crop_box,
    hflip_keypoints,
    jitter_bbox,
    pad_bbox,
    resize_image,
    resize_mask,
    square_bbox,
)
from unicorn.data.images import DatasetError, load_image, to_chw_tensor

__all__ = ["BBoxCropDataset"]


class BBoxCropDataset(UnicornDataset):
    """Square crops around annotated boxes (base class of the CUB and Pascal3D+ loaders).

    Args:
        records: annotation dicts (see module docstring).
        image_dir: folder that ``rel_path`` is relative to.
        img_size: side of the returned images.
        padding: fraction of the box size added on every side (0.05 CUB, 0.1 Pascal3D+).
        jitter: fraction of the box size by which training boxes move at random (same values).
        augment: jitter the box and flip at random (the reference does so for training only).
        eval_size: if set, masks and keypoints are given at this resolution instead of ``img_size`` (the
            reference evaluates CUB masks / PCK at 256).
        flip_perm: (K,) 0-based permutation swapping left and right keypoints, or None to drop keypoints.
        on_error: ``"raise"`` or ``"skip"`` unreadable images.

    Items (besides the common keys): ``keypoints`` (K, 3) ``(column, row, visible)`` in pixels of the returned
    mask's resolution, invisible ones at (0, 0, 0); ``flipped`` bool.
    """

    def __init__(
        self,
        records: list[dict[str, Any]],
        image_dir: str | Path,
        img_size: int = 64,
        padding: float = 0.05,
        jitter: float = 0.05,
        augment: bool = False,
        eval_size: int | None = None,
        flip_perm: np.ndarray | None = None,
        on_error: OnError = "raise",
    ) -> None:
        super().__init__(on_error)
        if not 0.0 <= jitter < 1.0:
            raise DatasetError(f"jitter must be in [0, 1) (a fraction of the box size), got {jitter}")
        self.records = records
        self.image_dir = Path(image_dir)
        self.img_size = int(img_size)
        self.padding = float(padding)
        self.jitter = float(jitter)
        self.augment = bool(augment)
        self.eval_size = None if eval_size is None else int(eval_size)
        self.flip_perm = None if flip_perm is None else np.asarray(flip_perm, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.records)

    def image_path(self, index: int) -> Path:
        return self.image_dir / str(self.records[index]["rel_path"])

    def square_crop_box(self, index: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """The square 0-based box of item ``index``, jittered when ``rng`` is given."""
        b = self.records[index]["bbox"]
        # MATLAB boxes are 1-based and inclusive
        bbox = np.array([b["x1"], b["y1"], b["x2"], b["y2"]], dtype=np.float64) - 1.0
        bbox = pad_bbox(bbox, self.padding)
        if rng is not None and self.jitter > 0:
            bbox = jitter_bbox(bbox, self.jitter, rng)
        return square_bbox(bbox)

    def load(self, index: int) -> dict[str, Any]:
        record = self.records[index]
        image = load_image(self.image_path(index), exif_orientation=False)  # annotations are on the stored grid
        mask = np.asarray(record["mask"], dtype=np.float32)
        if mask.shape != image.shape[:2]:
            mask = resize_mask(mask, image.shape[:2])
        rng = item_rng() if self.augment else None
        bbox = self.square_crop_box(index, rng)
        crop, mask_crop = crop_box(image, bbox, mask)
        side = int(bbox[2] - bbox[0] + 1)
        out_mask = self.eval_size or self.img_size
        image = resize_image(crop, (self.img_size, self.img_size))
        mask = resize_mask(mask_crop, (out_mask, out_mask))

        item: dict[str, Any] = {}
        keypoints = None
        if self.flip_perm is not None:
            parts = np.asarray(record["parts"], dtype=np.float64).reshape(3, -1).T.copy()  # (K, 3)
            visible = parts[:, 2] > 0
            # 1-based pixel centres -> 0-based, into the crop, then rescale keeping pixel centres aligned
            xy = parts[:, :2] - 1.0 - bbox[:2]
            xy = (xy + 0.5) * (out_mask / side) - 0.5
            keypoints = np.concatenate([xy, visible[:, None]], axis=1)
            keypoints[~visible] = 0.0

        flipped = rng is not None and rng.random() < 0.5
        if flipped:
            image, mask = image[:, ::-1], mask[:, ::-1]
            if keypoints is not None:
                keypoints = hflip_keypoints(keypoints, out_mask, self.flip_perm)
                keypoints[keypoints[:, 2] == 0] = 0.0

        R, T = dummy_pose()
        item.update(
            image=to_chw_tensor(image),
            mask=to_chw_tensor(mask),
            R=R,
            T=T,
            has_pose=torch.tensor(False),
            has_mask=torch.tensor(True),
            flipped=torch.tensor(flipped),
        )
        if keypoints is not None:
            item["keypoints"] = torch.from_numpy(keypoints.astype(np.float32))
        return item
