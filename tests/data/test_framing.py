"""Framing steps: boxes, crops, square padding and mirrored keypoints."""

from __future__ import annotations

import numpy as np
from PIL import Image

from unicorn.data.framing import crop_box, fit_and_pad, hflip_keypoints, jitter_bbox, pad_bbox, square_bbox


def test_square_bbox_and_padding() -> None:
    box = square_bbox(pad_bbox(np.array([10, 20, 29, 59]), 0.05))  # 20 x 40 box, padded by 1 x 2
    side = box[2] - box[0] + 1
    assert side == box[3] - box[1] + 1 == 44
    assert box[1] == 18 and box[3] == 61  # the long side keeps the padded extent


def test_moved_and_shrunk_boxes_keep_a_pixel() -> None:
    """A box's far corner never passes its near one: jittered by up to 0.49 of its size (a 2 x 2 box, whose corners
    then may cross by a pixel) or shrunk past its centre, the box still crops at least one pixel."""
    image = np.zeros((8, 8, 3), np.float32)
    rng = np.random.default_rng(0)
    boxes = [jitter_bbox(np.array([3.0, 3.0, 4.0, 4.0]), 0.49, rng) for _ in range(500)]
    boxes += [pad_bbox(np.array([0.0, 0.0, 7.0, 7.0]), frac) for frac in (-0.45, -0.49, -0.7)]
    for box in boxes:
        assert box[2] >= box[0] and box[3] >= box[1], box
        crop, _ = crop_box(image, np.round(box).astype(np.int64))
        assert crop.shape[0] >= 1 and crop.shape[1] >= 1
        assert square_bbox(box)[2] >= square_bbox(box)[0]


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
    """A 20 x 40 image with a row ramp (green), a column ramp (red) and a block (blue) against a hand layout: at 16
    pixels it is 8 x 16 (scale 0.4) at rows 4..11, equal to PIL's resize of it, rows 0..3 repeating row 4 and rows
    12..15 row 11; a tall image is laid out the same way across."""
    yy, xx = np.mgrid[0:20, 0:40]
    image = np.stack([xx / 39, yy / 19, ((xx >= 10) & (xx < 20) & (yy < 10)).astype(float)], -1).astype(np.float32)
    out = fit_and_pad(image, 16)
    assert out.shape == (16, 16, 3)
    block = np.stack(
        [np.asarray(Image.fromarray(image[..., c]).resize((16, 8), Image.Resampling.BILINEAR)) for c in range(3)], -1
    )
    assert np.allclose(out[4:12], block, atol=1e-6)
    assert np.array_equal(out[:4], np.broadcast_to(out[4], (4, 16, 3)))
    assert np.array_equal(out[12:], np.broadcast_to(out[11], (4, 16, 3)))
    assert (np.diff(out[4:12, :, 1], axis=0) > 0.05).all()  # the row ramp spans the block rows only
    assert out[4:6, 4:8, 2].min() > 0.5 and out[8:12, 4:8, 2].max() < 0.5 and out[4:6, 12:, 2].max() < 0.5
    tall = fit_and_pad(np.ascontiguousarray(image.transpose(1, 0, 2)), 16)
    assert np.allclose(tall, out.transpose(1, 0, 2), atol=1e-6)


def test_hflip_keypoints_is_an_involution() -> None:
    kps = np.array([[3.0, 4.0, 1.0], [10.0, 2.0, 1.0], [0.0, 0.0, 0.0]])
    perm = np.array([1, 0, 2])
    once = hflip_keypoints(kps, 16, perm)
    assert np.allclose(once[1, :2], [12.0, 4.0])  # keypoint 0 mirrored lands in slot 1
    assert np.allclose(hflip_keypoints(once, 16, perm), kps)
