"""Does each reconstruction have its own object's shape? Retrieval among the evaluated objects and spread.

- :func:`shape_retrieval`: whether each reconstruction is closer to its own object than to the other evaluated
  objects (top-k and reciprocal rank of the right object, ranked by Chamfer distance after
  :func:`normalize_shape`), which a model emitting one shape for every image scores at chance
  (:func:`retrieval_scores` ranks a given distance matrix);
- :func:`shape_spread`: how much the shapes of a set differ, and :func:`mesh_spread`, the same for meshes of one
  topology, vertex by vertex (no ground truth needed).
"""

from __future__ import annotations

import math

import torch

from unicorn.checks import ShapeError, check_points, check_shape

from .chamfer import chamfer_matrix
from .nn import Backend

__all__ = ["mesh_spread", "normalize_shape", "retrieval_scores", "shape_retrieval", "shape_spread"]


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
