"""Instance-level metrics: does a reconstruction carry *this* image's colour and shape, or the category mean's?

A model that outputs one mesh and one colour for every image can still score well on averaged shape and
silhouette metrics. These functions compare each image's reconstruction with what a predictor that ignores the
image would get:

- colour: :func:`mean_foreground_color` of the input and of the reconstruction, and :func:`color_errors`, the
  per-image error of the reconstruction's mean foreground colour beside the error of predicting one colour
  (the evaluated images' average) for every image; the ratio of their means is below 1 only when the
  reconstructions carry instance colour;
- shape: :func:`win_share`, the share of objects on which a model's per-object error is below a baseline's
  (e.g. Chamfer-L1 after ICP of the model and of the best single mean shape); :func:`shape_retrieval`, whether
  each reconstruction is closer to its own object than to the other evaluated objects (top-k and reciprocal
  rank of the right object, ranked by Chamfer distance after :func:`normalize_shape`), which a model emitting one
  shape for every image scores at chance; :func:`shape_spread`, how much the shapes of a set differ, and
  :func:`mesh_spread`, the same for meshes of one topology, vertex by vertex (no ground truth needed);
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

from unicorn.checks import ShapeError, check_points, check_shape

from .chamfer import chamfer_matrix
from .nn import Backend

__all__ = [
    "active_units",
    "code_spread",
    "color_errors",
    "flip_rate",
    "mean_foreground_color",
    "mesh_spread",
    "normalize_shape",
    "retrieval_scores",
    "rotation_accuracy",
    "shape_retrieval",
    "shape_spread",
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


def normalize_shape(points: torch.Tensor, per_axis: bool = False) -> torch.Tensor:
    """Each cloud centred on its mean and scaled to a unit RMS radius (one factor: proportions are kept).

    What one image cannot tell, the object's size (and its distance), is taken out; what it can, the shape and
    its proportions, is left.

    Args:
        points: (B, N, 3) clouds.
        per_axis: scale each coordinate axis to a unit RMS instead (``mean_n x_a^2 = 1 / 3`` for each axis a),
            which takes out an anisotropic scale along the axes as well: what is left is the shape beyond its
            proportions.

    Returns:
        (B, N, 3) with ``mean_n x = 0`` and ``mean_n |x|^2 = 1`` (a cloud of one point stays at 0).

    Example:
        >>> x = normalize_shape(torch.tensor([[[0.0, 0.0, 2.0], [0.0, 0.0, 4.0]]]))
        >>> x.tolist()
        [[[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]]
    """
    check_points(points, "points")
    centred = points - points.mean(dim=1, keepdim=True)
    if per_axis:
        radius = (3 * centred.square().mean(dim=1, keepdim=True)).sqrt()  # (B, 1, 3)
    else:
        radius = centred.square().sum(dim=-1).mean(dim=1).sqrt()[:, None, None]  # (B, 1, 1)
    return centred / radius.clamp_min(torch.finfo(points.dtype).tiny)


def retrieval_scores(
    distances: torch.Tensor, targets: torch.Tensor, ks: tuple[int, ...] = (1, 3)
) -> dict[str, torch.Tensor]:
    """Top-k hits and reciprocal rank of each query's right candidate, from query-candidate distances.

    Ties are broken at random, in expectation: with ``l`` candidates strictly closer than the right one and ``t``
    others at the same distance, the right one's rank is uniform over ``l + 1 ... l + t + 1``, so a query scores
    ``P(rank <= k)`` and ``E[1 / rank]``. A query whose distances are all equal scores chance, ``k / C``.

    Args:
        distances: (Q, C) distance of each query to each candidate (lower: closer).
        targets: (Q,) long, the index of each query's right candidate.
        ks: the k of the top-k hits.

    Returns:
        ``{"top<k>": (Q,) ..., "rr": (Q,)}``: per query the (expected) top-k hit in [0, 1] and reciprocal rank;
        their means over the queries are the top-k accuracy and the mean reciprocal rank (MRR).

    Example:
        >>> d = torch.tensor([[0.1, 0.2, 0.3], [0.1, 0.2, 0.3]])
        >>> s = retrieval_scores(d, torch.tensor([0, 2]), ks=(1, 2))
        >>> s["top1"].tolist(), s["top2"].tolist(), [round(v, 3) for v in s["rr"].tolist()]
        ([1.0, 0.0], [1.0, 0.0], [1.0, 0.333])
    """
    dims = check_shape(distances, "Q, C", "distances")
    if dims["C"] == 0:
        raise ShapeError(f"distances has no candidate (C = 0), shape {tuple(distances.shape)}")
    targets = torch.as_tensor(targets, device=distances.device).long()
    check_shape(targets, "Q", "targets", dims)
    if targets.numel() and not (0 <= int(targets.min()) and int(targets.max()) < distances.shape[1]):
        raise ValueError(f"targets must index the {distances.shape[1]} candidates")
    d = distances.double()
    own = d.gather(1, targets[:, None])  # (Q, 1)
    closer = (d < own).sum(dim=1).double()  # (Q,)
    tied = (d == own).sum(dim=1).double()  # the right one included: >= 1
    out = {f"top{k}": ((k - closer) / tied).clamp(0.0, 1.0) for k in ks}
    # E[1 / rank] over ranks closer + 1 ... closer + tied: a difference of harmonic numbers (digamma(n + 1) = H_n)
    harmonic = (torch.digamma(closer + tied + 1) - torch.digamma(closer + 1)) / tied
    out["rr"] = torch.where(tied == 1, 1.0 / (closer + 1), harmonic)  # exact without a tie
    return out


def shape_retrieval(
    queries: torch.Tensor,
    rotations: torch.Tensor,
    candidates: torch.Tensor,
    targets: torch.Tensor,
    ks: tuple[int, ...] = (1, 3),
    *,
    backend: Backend = "auto",
    workers: int = 1,
) -> dict[str, torch.Tensor]:
    """Retrieval of each image's object among the candidate objects from the image's reconstruction.

    Each query (a reconstruction in its image's view coordinates, ``x_view = x @ R + T``) is compared with every
    candidate object seen in the same view, i.e. the candidate's points at the query image's ground-truth pose
    ``(R, T)``; both are normalised with :func:`normalize_shape` (the object's size is what one image cannot
    know), and the candidates are ranked by Chamfer-L1 (:func:`~unicorn.metrics.chamfer_matrix`). Centring takes
    out ``T``, and a rotation moves both clouds alike, so each query is compared in its candidates' object frame
    (rotated by ``R^T``) and only ``R`` is needed.

    Args:
        queries: (Q, N, 3) points of the reconstructions, each in its image's view coordinates.
        rotations: (Q, 3, 3) the ground-truth rotation of each query's image.
        candidates: (C, M, 3) points of the candidate objects in their object frame (the frame of the ground-truth
            poses).
        targets: (Q,) long, the index of each query's object among the candidates.
        ks: the k of the top-k hits.
        backend: nearest-neighbour backend.
        workers: kdtree query threads.

    Returns:
        :func:`retrieval_scores` of the (Q, C) distances, plus ``"distances"``.
    """
    check_points(queries, "queries")
    check_points(candidates, "candidates")
    check_shape(rotations, "Q, 3, 3", "rotations", {"Q": queries.shape[0]})
    in_object_frame = normalize_shape(queries) @ rotations.to(queries).transpose(1, 2)
    distances = chamfer_matrix(
        in_object_frame, normalize_shape(candidates.to(queries)), factor=1.0, backend=backend, workers=workers
    )
    return {**retrieval_scores(distances, targets, ks), "distances": distances}


def shape_spread(
    clouds: torch.Tensor,
    objects: torch.Tensor | None = None,
    per_axis: bool = False,
    *,
    backend: Backend = "auto",
    workers: int = 1,
) -> float:
    """How much the shapes of a set differ: the mean Chamfer-L1 between two of them, normalised, of different objects.

    Each cloud is normalised with :func:`normalize_shape` in its own frame (no pose is involved); the mean runs
    over the pairs of clouds of different objects (two views of one object are not compared). A set of one shape
    repeated, at any scale, spreads 0 when its clouds are sampled alike (e.g. each mesh with the same seed).

    Args:
        clouds: (P, N, 3) one cloud per image.
        objects: (P,) the object each image shows; None: every image shows a different object.
        per_axis: normalise each axis of the clouds' frame (:func:`normalize_shape`): the spread beyond the
            proportions along those axes (a set of one shape stretched along them spreads 0).
        backend: nearest-neighbour backend.
        workers: kdtree query threads.

    Returns:
        The mean distance (factor 1); NaN without a pair of different objects.
    """
    check_points(clouds, "clouds")
    P = clouds.shape[0]
    objects = torch.arange(P) if objects is None else torch.as_tensor(objects).cpu()
    check_shape(objects, "P", "objects", {"P": P})
    pairs = objects[:, None] != objects[None, :]
    if not bool(pairs.any()):
        return math.nan
    normed = normalize_shape(clouds, per_axis)
    distances = chamfer_matrix(normed, normed, factor=1.0, backend=backend, workers=workers).cpu()
    return float(distances.double()[pairs].mean())


def mesh_spread(verts: torch.Tensor, per_axis: bool = True) -> float:
    """How much meshes of one topology differ: the mean distance of a vertex to its mean position over the set.

    Each mesh is normalised with :func:`normalize_shape` first, so the figure is in units of the RMS radius and
    a set of one shape at several sizes (``per_axis``: also stretched along the axes) spreads 0. It needs no
    ground truth: on the template meshes a model predicts for a batch of images, it says whether the shape
    follows the image beyond the proportions.

    Args:
        verts: (B, V, 3) B meshes with the same vertex order (e.g. deformed templates).
        per_axis: normalise each axis (:func:`normalize_shape`): the spread beyond the proportions.

    Returns:
        ``mean_b mean_v |x_bv - mean_b' x_b'v|`` over the normalised meshes; 0 for a single mesh.

    Example:
        >>> box = torch.tensor([[[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
        >>> mesh_spread(torch.cat([box, 2 * box]))
        0.0
    """
    check_points(verts, "verts")
    normed = normalize_shape(verts.double(), per_axis)
    return float((normed - normed.mean(dim=0, keepdim=True)).norm(dim=-1).mean())
