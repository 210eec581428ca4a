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

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from unicorn.data.common import OnError, SkippedFileWarning, UnicornDataset, dummy_pose, item_rng
from unicorn.data.framing import (
    crop_box,
    hflip_keypoints,
    jitter_bbox,
    pad_bbox,
    resize_image,
    resize_mask,
    square_bbox,
)
from unicorn.data.images import (
    RGB_BYTES_PER_PIXEL,
    DatasetError,
    ImageLoadError,
    load_image,
    max_image_bytes,
    to_chw_tensor,
)

__all__ = ["AnnotationError", "BBoxCropDataset"]

_BOX_FIELDS = ("x1", "y1", "x2", "y2")


def _box_as_written(record: dict[str, Any]) -> np.ndarray:
    """``(x1, y1, x2, y2)`` of a record's box as the file has it (1-based, inclusive), float64."""
    return np.array([record["bbox"][k] for k in _BOX_FIELDS], dtype=np.float64)


def _box(record: dict[str, Any]) -> np.ndarray:
    """(4,) float64 ``(x1, y1, x2, y2)`` of a record's box, 0-based."""
    return _box_as_written(record) - 1.0


class AnnotationError(ImageLoadError):
    """A record whose annotations do not fit its image (a mask of another size, a box off the image or too large
    to crop): the item cannot be made, and is skipped like an unreadable image under ``on_error="skip"``."""

    lead = "bad annotations for"


class BBoxCropDataset(UnicornDataset):
    """Square crops around annotated boxes (base class of the CUB and Pascal3D+ loaders).

    Args:
        records: annotation dicts (see module docstring).
        image_dir: folder that ``rel_path`` is relative to.
        img_size: side of the returned images.
        padding: fraction of the box size added on every side (0.05 CUB, 0.1 Pascal3D+).
        jitter: fraction of the box size by which training boxes move at random (same values), in [0, 0.5).
        augment: jitter the box and flip at random (the reference does so for training only).
        eval_size: if set, masks and keypoints are given at this resolution instead of ``img_size`` (the
            reference evaluates CUB masks / PCK at 256).
        flip_perm: (K,) 0-based permutation swapping left and right keypoints, or None to drop keypoints.
        on_error: ``"raise"`` or ``"skip"`` unreadable images and malformed records.
        source: where the records come from, named in errors (the annotation file).

    Records are checked when the dataset is made (:meth:`record_problem`): a malformed one (a missing field, a box
    that is not finite, inverted or under 2 pixels, a mask that is not 2-D, keypoints not (3, K)) raises a
    :class:`~unicorn.data.images.DatasetError` naming it, or with ``on_error="skip"`` is left out with one
    warning. What needs the image (the mask's size, the box on the image) is checked when an item is read
    (:class:`AnnotationError`).

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
        source: str | Path = "the annotations",
    ) -> None:
        super().__init__(on_error)
        if not 0.0 <= jitter < 0.5:  # from 0.5 on, a box's opposite corners may cross
            raise DatasetError(f"jitter must be in [0, 0.5) (a fraction of the box size), got {jitter}")
        self.image_dir = Path(image_dir)
        self.img_size = int(img_size)
        self.padding = float(padding)
        self.jitter = float(jitter)
        self.augment = bool(augment)
        self.eval_size = None if eval_size is None else int(eval_size)
        self.flip_perm = None if flip_perm is None else np.asarray(flip_perm, dtype=np.int64)
        if self.flip_perm is not None and sorted(self.flip_perm.tolist()) != list(range(len(self.flip_perm))):
            raise DatasetError(
                f"the keypoints' flip permutation must hold each index 0..{len(self.flip_perm) - 1} once (1-based "
                f"in the MATLAB files), got {(self.flip_perm + 1).tolist()} (1-based)"
            )
        self.records = self._checked(records, str(source))

    def record_problem(self, record: Any) -> str | None:
        """What makes ``record`` unusable, in words, or None (subclasses add their own fields' checks)."""
        if not isinstance(record, dict):
            return f"not a struct but a {type(record).__name__}"
        fields = ("rel_path", "bbox", "mask") + (("parts",) if self.flip_perm is not None else ())
        missing = [name for name in fields if name not in record]
        if missing:
            return f"no {missing[0]!r} field"
        if not isinstance(record["rel_path"], str) or not record["rel_path"]:
            return f"rel_path must be a file name, got {record['rel_path']!r}"
        b = record["bbox"]
        if not isinstance(b, dict) or any(k not in b for k in _BOX_FIELDS):
            return "bbox must be a struct with fields x1, y1, x2, y2"
        try:
            box = _box_as_written(record)
        except (TypeError, ValueError):
            return "bbox's x1, y1, x2, y2 must be numbers"
        if box.shape != (4,) or not np.isfinite(box).all():
            return f"bbox's x1, y1, x2, y2 must be finite numbers, got {box.tolist()}"
        if box[2] - box[0] < 1 or box[3] - box[1] < 1:
            return f"bbox (x1, y1, x2, y2) = {box.tolist()} must be at least 2 pixels wide and high (x1 < x2, y1 < y2)"
        mask = np.asarray(record["mask"])
        if mask.ndim != 2 or 0 in mask.shape:
            return f"mask must be an (H, W) array, got shape {mask.shape}"
        if self.flip_perm is not None:
            shape, K = np.shape(record["parts"]), len(self.flip_perm)
            if shape != (3, K):
                what = f"x, y and visibility of the {K} keypoints of the flip permutation"
                return f"parts must be (3, {K}) ({what}), got {shape}"
        return None

    def _checked(self, records: list[Any], source: str) -> list[dict[str, Any]]:
        """``records`` less the malformed ones when skipping; otherwise the first one raises."""
        if not records:
            raise DatasetError(f"{source} holds no records")
        problems = [(i, p) for i, p in enumerate(map(self.record_problem, records)) if p is not None]
        if not problems:
            return records
        first, problem = problems[0]
        said = f"record {first + 1} of {source}: {problem}"
        if self.on_error == "raise" or len(problems) == len(records):
            more = f" ({len(problems)} of its {len(records)} records are malformed)" if len(problems) > 1 else ""
            raise DatasetError(f"{said}{more}")
        warnings.warn(
            f"skipping {len(problems)} of {len(records)} records of {source}; the first: {said}",
            SkippedFileWarning,
            stacklevel=3,
        )
        bad = {i for i, _ in problems}
        return [r for i, r in enumerate(records) if i not in bad]

    def __len__(self) -> int:
        return len(self.records)

    def image_path(self, index: int) -> Path:
        return self.image_dir / str(self.records[index]["rel_path"])

    def square_crop_box(self, index: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """The square 0-based box of item ``index``, jittered when ``rng`` is given."""
        bbox = pad_bbox(_box(self.records[index]), self.padding)
        if rng is not None and self.jitter > 0:
            bbox = jitter_bbox(bbox, self.jitter, rng)
        return square_bbox(bbox)

    def _check_on_image(self, index: int, image: np.ndarray, mask: np.ndarray, bbox: np.ndarray) -> None:
        """The record's mask and square box ``bbox`` (0-based) against its image (H, W, 3)."""
        H, W = image.shape[:2]
        path = self.image_path(index)
        if mask.shape != (H, W):
            raise AnnotationError(path, f"its mask is {mask.shape[0]} x {mask.shape[1]} (H x W), the image {H} x {W}")
        x1, y1, x2, y2 = _box(self.records[index]).tolist()
        if x2 < 0 or y2 < 0 or x1 > W - 1 or y1 > H - 1:
            raise AnnotationError(path, f"its box (0-based) {[x1, y1, x2, y2]} lies outside the {W} x {H} image")
        side, limit = int(bbox[2] - bbox[0] + 1), max_image_bytes()
        if limit is not None and side * side * RGB_BYTES_PER_PIXEL > limit:
            raise AnnotationError(
                path, f"its box makes a crop of {side} x {side} pixels, over the image limit of {limit} bytes"
            )

    def load(self, index: int) -> dict[str, Any]:
        record = self.records[index]
        image = load_image(self.image_path(index), exif_orientation=False)  # annotations are on the stored grid
        mask = np.asarray(record["mask"], dtype=np.float32)
        rng = item_rng() if self.augment else None
        bbox = self.square_crop_box(index, rng)
        self._check_on_image(index, image, mask, bbox)
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
