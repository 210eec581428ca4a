"""Instance-level metrics: does a reconstruction carry *this* image's colour and shape, or the category mean's?

A model that outputs one mesh and one colour for every image can still score well on averaged shape and
silhouette metrics. These functions compare each image's reconstruction with what a predictor that ignores the
image would get:

- colour: :func:`mean_foreground_color` of the input and of the reconstruction, and :func:`color_errors`, the
  per-image error of the reconstruction's mean foreground colour beside the error of predicting one colour
  (the evaluated images' average) for every image; the ratio of their means is below 1 only when the
  reconstructions carry instance colour;
- shape: :func:`win_share`, the share of objects on which a model's per-object error is below a baseline's
  (e.g. Chamfer-L1 after ICP of the model and of the best single mean shape); shape retrieval and spread are in
  :mod:`unicorn.metrics.shapes`;
- pose: :func:`rotation_accuracy` (error below a threshold) and :func:`flip_rate` (error above a threshold
  near 180 degrees: the object predicted turned round), on per-image geodesic errors;
- codes: :func:`code_spread` (standard deviation of each code dimension across a batch: 0 for a code that
  ignores the image) and :func:`active_units` (hidden ReLU units active for at least one image of a batch:
  a unit never active is dead and passes no gradient).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from unicorn.checks import ShapeError, check_shape

__all__ = [
    "active_units",
    "code_spread",
    "color_errors",
    "flip_rate",
    "mean_foreground_color",
    "rotation_accuracy",
    "win_share",
]


def mean_foreground_color(
    images: torch.Tensor, masks: torch.Tensor, threshold: float = 0.5, interior: int = 0
) -> torch.Tensor:
    """Mean colour of each image's foreground pixels.

    Args:
        images: (B, C, H, W) colours (C = 3 for RGB).
        masks: (B, H, W) or (B, 1, H, W) foreground masks or alphas (bool or float), binarised with
            ``mask >= threshold``.
        threshold: binarisation threshold.
        interior: r >= 0: keep only the foreground pixels whose (2r + 1) x (2r + 1) neighbourhood is all
            foreground (the mask eroded by r pixels). A border pixel mixes the object's colour with the
            background's (anti-aliasing), and which pixels are border depends on the silhouette, so comparing
            border colours of two silhouettes measures their shapes as much as their colours. An image whose
            eroded mask is empty keeps its whole mask (thin objects at low resolution).

    Returns:
        (B, C) mean colour over the pixels inside the mask; NaN for an image with an empty mask.

    Example:
        >>> img = torch.tensor([[[[0.0, 1.0]], [[0.5, 0.5]], [[1.0, 0.0]]]])  # (1, 3, 1, 2)
        >>> mean_foreground_color(img, torch.tensor([[[1.0, 0.0]]])).tolist()
        [[0.0, 0.5, 1.0]]
    """
    dims = check_shape(images, "B, C, H, W", "images")
    check_shape(masks, "B, H, W | B, 1, H, W", "masks", dims)
    if masks.dim() == 4:
        masks = masks[:, 0]
    if interior < 0:
        raise ValueError(f"interior must be >= 0, got {interior}")
    w = (masks.to(images.device).float() >= threshold).to(images.dtype)  # (B, H, W)
    if interior > 0:
        # erosion = a min filter = -maxpool(-w); outside the image counts as foreground: the frame cutting an
        # object is not a silhouette border, its pixels are not mixed
        k = 2 * interior + 1
        eroded = -F.max_pool2d(F.pad(-w.unsqueeze(1), [interior] * 4, value=-1.0), k, stride=1).squeeze(1)
        w = torch.where((eroded.sum(dim=(1, 2)) > 0)[:, None, None], eroded, w)
    total = w.sum(dim=(1, 2))  # (B,)
    colors = (images * w.unsqueeze(1)).sum(dim=(2, 3)) / total.clamp_min(1.0).unsqueeze(1)
    return torch.where(total.unsqueeze(1) > 0, colors, torch.full_like(colors, math.nan))


def color_errors(
    pred_colors: torch.Tensor, gt_colors: torch.Tensor, reference: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image colour error of a model and of a predictor of one colour for every image.

    The error is the L1 distance averaged over the channels, ``mean_c |a_c - b_c|``.

    Args:
        pred_colors: (B, C) the reconstructions' mean foreground colours.
        gt_colors: (B, C) the inputs' mean foreground colours.
        reference: (C,) the colour the baseline predicts for every image; None: the mean of ``gt_colors`` over
            the images (NaN rows left out), i.e. the best constant colour one can predict without the image.

    Returns:
        ``(model, baseline)``, each (B,): the model's error and the baseline's, NaN where a colour is NaN.

    Example:
        >>> gt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        >>> model, base = color_errors(gt, gt)
        >>> model.tolist(), base.tolist()
        ([0.0, 0.0], [0.3333333432674408, 0.3333333432674408])
    """
    dims = check_shape(pred_colors, "B, C", "pred_colors")
    check_shape(gt_colors, "B, C", "gt_colors", dims)
    gt_colors = gt_colors.to(pred_colors)
    if reference is None:
        valid = ~torch.isnan(gt_colors).any(dim=1)
        if not bool(valid.any()):
            raise ValueError("no image has a foreground colour: the mean colour is undefined")
        reference = gt_colors[valid].mean(dim=0)
    check_shape(reference, "C", "reference", dims)
    reference = reference.to(pred_colors)
    model = (pred_colors - gt_colors).abs().mean(dim=1)
    baseline = (reference.unsqueeze(0) - gt_colors).abs().mean(dim=1)
    return model, baseline


def win_share(errors: torch.Tensor, baseline_errors: torch.Tensor) -> float:
    """Share of objects on which ``errors`` is below ``baseline_errors`` (lower is better for both).

    A tie counts half; pairs with a NaN are left out.

    Args:
        errors: (N,) the model's per-object errors.
        baseline_errors: (N,) the baseline's errors on the same objects.

    Returns:
        The share in [0, 1]; NaN when no pair is complete.

    Example:
        >>> win_share(torch.tensor([0.1, 0.3, 0.2, 0.5]), torch.tensor([0.2, 0.2, 0.2, 0.6]))
        0.625
    """
    errors, baseline_errors = torch.as_tensor(errors), torch.as_tensor(baseline_errors)
    check_shape(baseline_errors, "N", "baseline_errors", check_shape(errors, "N", "errors"))
    baseline_errors = baseline_errors.to(errors)
    keep = ~(torch.isnan(errors) | torch.isnan(baseline_errors))
    if not bool(keep.any()):
        return math.nan
    a, b = errors[keep].double(), baseline_errors[keep].double()
    return float(((a < b).double() + 0.5 * (a == b).double()).mean())


def _check_errors(errors: torch.Tensor) -> torch.Tensor:
    errors = torch.as_tensor(errors)
    check_shape(errors, "N", "errors")
    if errors.numel() == 0:
        raise ValueError(f"errors must be a non-empty (N,) tensor of degrees, got shape {tuple(errors.shape)}")
    return errors


def rotation_accuracy(errors: torch.Tensor, threshold: float = 30.0) -> float:
    """Share of images whose rotation error (degrees, (N,)) is below ``threshold`` (Acc_{pi/6} for 30).

    Example:
        >>> rotation_accuracy(torch.tensor([5.0, 29.0, 31.0, 179.0]))
        0.5
    """
    return float((_check_errors(errors) < threshold).double().mean())


def flip_rate(errors: torch.Tensor, threshold: float = 150.0) -> float:
    """Share of images whose rotation error (degrees, (N,)) is above ``threshold``: predicted turned round.

    Reported separately from the accuracy: a model confusing front and back has errors near 180 degrees,
    which an average or a median error mixes up with merely imprecise poses.

    Example:
        >>> flip_rate(torch.tensor([5.0, 29.0, 160.0, 179.0]))
        0.5
    """
    return float((_check_errors(errors) > threshold).double().mean())


def code_spread(codes: torch.Tensor, active_dims: int | None = None) -> torch.Tensor:
    """Standard deviation of each code dimension across a batch (population std, divisor B).

    Args:
        codes: (B, C) codes of B images.
        active_dims: keep only the first ``active_dims`` dimensions (progressive conditioning); None: all.

    Returns:
        (C',) the spread of each (kept) dimension; 0 for a dimension that is the same for every image.

    Example:
        >>> code_spread(torch.tensor([[0.0, 1.0], [2.0, 1.0]])).tolist()
        [1.0, 0.0]
    """
    if check_shape(codes, "B, C", "codes")["B"] == 0:
        raise ShapeError(f"codes has an empty batch dimension, shape {tuple(codes.shape)}")
    if active_dims is not None:
        if not 0 <= active_dims <= codes.shape[1]:
            raise ValueError(f"active_dims must be in [0, {codes.shape[1]}], got {active_dims}")
        codes = codes[:, :active_dims]
    if codes.shape[1] == 0:
        return codes.new_zeros(0)
    return codes.double().std(dim=0, correction=0).to(codes.dtype)


def active_units(activations: torch.Tensor, threshold: float = 0.0) -> torch.Tensor:
    """Which hidden units are active (output above ``threshold``) for at least one image of a batch.

    Args:
        activations: (B, U) post-ReLU outputs of one hidden layer for B images.
        threshold: activity threshold (0 for ReLU units: a unit at 0 for every input passes no gradient).

    Returns:
        (U,) bool.

    Example:
        >>> active_units(torch.tensor([[0.0, 0.5, 0.0], [0.0, 0.0, 0.2]])).tolist()
        [False, True, True]
    """
    if check_shape(activations, "B, U", "activations")["B"] == 0:
        raise ShapeError(f"activations has an empty batch dimension, shape {tuple(activations.shape)}")
    return (activations > threshold).any(dim=0)
