"""Framing steps: boxes, crops, square padding and mirrored keypoints."""

from __future__ import annotations

import numpy as np

from unicorn.data.framing import crop_box, fit_and_pad, hflip_keypoints, pad_bbox, square_bbox


def test_square_bbox_and_padding() -> None:
    box = square_bbox(pad_bbox(np.array([10, 20, 29, 59]), 0.05))  # 20 x 40 box, padded by 1 x 2
    side = box[2] - box[0] + 1
    assert side == box[3] - box[1] + 1 == 44
    assert box[1] == 18 and box[3] == 61  # the long side keeps the padded extent


def test_crop_box_replicates_border_and_zeroes_mask() -> None:
    image = np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    mask = np.ones((4, 5), np.float32)
    crop, mcrop = crop_box(image, np.array([-2, -1, 6, 7]), mask)
    assert crop.shape == (9, 9, 3) and mcrop.shape == (9, 9)
    assert np.array_equal(crop[0, 0], image[0, 0]) and np.array_equal(crop[-1, -1], image[-1, -1])
    assert np.array_equal(crop[1:5, 2:7], image)
    assert mcrop.sum() == 20 and mcrop[0].sum() == 0 and mcrop[:, 0].sum() == 0
    # a box entirely outside the image still gives its full size
    crop, mcrop = crop_box(image, np.array([10, 10, 12, 13]), mask)
    assert crop.shape == (4, 3, 3) and mcrop.sum() == 0


def test_fit_and_pad_keeps_aspect() -> None:
    image = np.zeros((20, 40, 3), np.float32)
    image[:, :, 0] = 1.0
    out = fit_and_pad(image, 16)
    assert out.shape == (16, 16, 3) and np.allclose(out[..., 0], 1.0)


def test_hflip_keypoints_is_an_involution() -> None:
    kps = np.array([[3.0, 4.0, 1.0], [10.0, 2.0, 1.0], [0.0, 0.0, 0.0]])
    perm = np.array([1, 0, 2])
    once = hflip_keypoints(kps, 16, perm)
    assert np.allclose(once[1, :2], [12.0, 4.0])  # keypoint 0 mirrored lands in slot 1
    assert np.allclose(hflip_keypoints(once, 16, perm), kps)
