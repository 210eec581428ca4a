"""Mask IoU as UNICORN's CUB evaluation computes it."""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

from ..checks import check_shape

__all__ = ["mask_iou"]


def _as_bhw(mask: torch.Tensor, name: str) -> torch.Tensor:
    check_shape(mask, "B, H, W | B, 1, H, W", name)
    if mask.dim() == 4:
        mask = mask[:, 0]
    if mask.numel() == 0:
        raise ValueError(f"{name} is empty, shape {tuple(mask.shape)}")
    if mask.dtype == torch.bool:
        return mask.float()
    if not mask.is_floating_point():
        raise TypeError(f"{name} must be bool or floating point, got {mask.dtype}")
    return mask


def mask_iou(
    pred: torch.Tensor,
    gt: torch.Tensor,
    *,
    threshold: float = 0.5,
    reduction: Literal["mean", "none"] = "mean",
) -> torch.Tensor:
    """IoU between predicted silhouettes (alpha) and ground-truth masks, per image, then averaged.

    The prediction is bilinearly resized to the ground-truth size when they differ and binarised with
    ``pred > threshold``; then ``IoU = sum(pred * gt) / sum(clamp(pred + gt, 0, 1))`` per image, with ``gt``
    used as given (binary masks in practice). An image where both masks are empty scores 1.

    Args:
        pred: (B, H', W') or (B, 1, H', W') predicted alpha in [0, 1] (float or bool).
        gt: (B, H, W) or (B, 1, H, W) ground-truth masks in [0, 1] (float or bool).
        threshold: binarisation threshold of the prediction.
        reduction: ``"mean"`` for the average over images, ``"none"`` for the (B,) per-image values.

    Returns:
        scalar mean IoU, or (B,) per-image IoU.

    Example:
        >>> pred = torch.tensor([[[0.9, 0.6], [0.2, 0.0]]])
        >>> gt = torch.tensor([[[1.0, 0.0], [1.0, 0.0]]])
        >>> round(mask_iou(pred, gt).item(), 4)
        0.3333
    """
    pred, gt = _as_bhw(pred, "pred"), _as_bhw(gt, "gt")
    if pred.shape[0] != gt.shape[0]:
        raise ValueError(f"batch sizes differ: pred has {pred.shape[0]}, gt has {gt.shape[0]}")
    if reduction not in ("mean", "none"):
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    gt = gt.to(device=pred.device, dtype=pred.dtype)
    if pred.shape[-2:] != gt.shape[-2:]:
        pred = F.interpolate(pred.unsqueeze(1), size=gt.shape[-2:], mode="bilinear", align_corners=False)[:, 0]
    binary = (pred > threshold).to(pred.dtype)
    inter = (binary * gt).sum(dim=(1, 2))
    union = (binary + gt).clamp(0, 1).sum(dim=(1, 2))
    iou = torch.where(union > 0, inter / union.clamp_min(torch.finfo(pred.dtype).tiny), torch.ones_like(union))
    return iou.mean() if reduction == "mean" else iou
