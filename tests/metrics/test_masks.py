import pytest
import torch

from unicorn.metrics.masks import mask_iou


def test_hand_computed():
    pred = torch.tensor(
        [
            [[0.9, 0.6, 0.0], [0.51, 0.5, 0.0], [0.0, 0.0, 0.0]],  # 0.5 is not > 0.5
            [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]],
        ]
    )
    gt = torch.tensor(
        [
            [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]],
            [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        ]
    )
    # image 0: pred {00, 01, 10}, gt {00, 10, 11}: inter 2, union 4; image 1: 1 / 9
    per_image = mask_iou(pred, gt, reduction="none")
    torch.testing.assert_close(per_image, torch.tensor([0.5, 1 / 9]))
    assert mask_iou(pred, gt).item() == pytest.approx((0.5 + 1 / 9) / 2)
    assert mask_iou(pred.unsqueeze(1), gt.bool().unsqueeze(1)).item() == pytest.approx((0.5 + 1 / 9) / 2)


def test_resize_empty_and_threshold():
    pred = torch.zeros(1, 8, 8)
    pred[:, :4] = 1.0  # top half
    gt = torch.zeros(1, 4, 4)
    gt[:, :2, :2] = 1.0  # top-left quarter
    assert mask_iou(pred, gt).item() == pytest.approx(0.5)
    assert mask_iou(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4)).item() == 1.0
    assert mask_iou(torch.full((1, 2, 2), 0.4), torch.ones(1, 2, 2), threshold=0.3).item() == 1.0


def test_invalid_inputs():
    with pytest.raises(ValueError, match="batch"):
        mask_iou(torch.zeros(2, 4, 4), torch.zeros(3, 4, 4))
    with pytest.raises(ValueError, match="shape"):
        mask_iou(torch.zeros(2, 3, 4, 4), torch.zeros(2, 4, 4))
    with pytest.raises(TypeError, match="bool or floating"):
        mask_iou(torch.zeros(2, 4, 4, dtype=torch.long), torch.zeros(2, 4, 4))
