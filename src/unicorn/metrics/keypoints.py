"""PCK by keypoint transfer between image pairs, UNICORN's CUB protocol.

For a pair (source, target) of test images, each reconstructed as a posed mesh with the same topology:

1. the source mesh's *visible* vertices (those of faces hit by a hard rasterisation, computed by the caller)
   are projected to the source image with the source camera;
2. each ground-truth source keypoint takes the visible vertex whose projection is nearest in 2D;
3. the same vertex of the target mesh is projected with the target camera (no visibility test in the target);
   that is the transferred keypoint;
4. it is correct when within ``alpha * S`` pixels of the target's ground-truth keypoint, ``S`` being the image
   side (256 for CUB's padded square crops).

Both directions of every pair are evaluated, only keypoints visible in both images count, and
``PCK@alpha = #correct / #valid`` pooled over all pairs and directions, for alpha in {0.05, 0.1, 0.15}.

Pairs: 10,000 pairs from repeated seeded permutations of the test images, the first half of each permutation
against the second, seed ``123 + (number of pairs drawn so far)``, NumPy's legacy ``RandomState``; see
:func:`keypoint_pairs`. When the N images form at most that many ordered pairs (``N (N - 1) <= 10,000``, N <= 100),
:func:`keypoint_transfer_pck` uses every ordered pair once instead: the exact value the draw estimates, at a
fraction of its cost.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from unicorn.checks import check_rotations, check_shape, check_translations
from unicorn.geometry.cameras import PerspectiveCamera, image_hw

__all__ = ["keypoint_pairs", "keypoint_transfer_pck", "pck", "project_vertices", "transfer_keypoints"]


def keypoint_pairs(num_images: int, num_pairs: int = 10000, seed_offset: int = 123) -> tuple[np.ndarray, np.ndarray]:
    """Source and target image indices of the evaluation pairs, as UNICORN's keypoint evaluation draws them.

    While fewer than ``num_pairs`` pairs exist, a permutation of the images is drawn with
    ``np.random.RandomState(seed_offset + pairs_so_far)``; its first ``n // 2`` entries become sources and its
    last ``n // 2`` targets (for odd ``n`` the middle image is left out of that round, as the reference's
    ``indices[:middle]`` and ``indices[-middle:]`` leave it). The first ``num_pairs`` pairs are kept; an image is
    never paired with itself.

    Args:
        num_images: n >= 2 test images.
        num_pairs: pairs to draw.
        seed_offset: 123 in the reference.

    Returns:
        src: (num_pairs,) int64 indices; tgt: (num_pairs,) int64 indices.

    Example:
        >>> s, t = keypoint_pairs(4, 4)
        >>> s.shape, bool((s != t).all())
        ((4,), True)
    """
    if num_images < 2:
        raise ValueError(f"need at least 2 images to form pairs, got {num_images}")
    if num_pairs < 1:
        raise ValueError(f"num_pairs must be positive, got {num_pairs}")
    half = num_images // 2
    src: list[np.ndarray] = []
    tgt: list[np.ndarray] = []
    drawn = 0
    while drawn < num_pairs:
        perm = np.random.RandomState(seed_offset + drawn).permutation(num_images)
        src.append(perm[:half])
        tgt.append(perm[num_images - half :])
        drawn += half
    return (
        np.concatenate(src)[:num_pairs].astype(np.int64),
        np.concatenate(tgt)[:num_pairs].astype(np.int64),
    )


def project_vertices(
    verts: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    image_size: int | tuple[int, int],
    camera: PerspectiveCamera | None = None,
) -> torch.Tensor:
    """Pixel positions (column, row) of mesh vertices seen by their cameras.

    Args:
        verts: (B, V, 3) vertices in the object frame.
        R: (B, 3, 3) world-to-view rotations (``x_view = x @ R + T``).
        T: (B, 3) translations.
        image_size: S or (H, W) of the image the keypoints are expressed in.
        camera: the projection, ``PerspectiveCamera(fov=30)`` (UNICORN's) by default.

    Returns:
        (B, V, 2) pixel coordinates (column, row), pixel centres at integers.
    """
    camera = PerspectiveCamera(fov=30.0) if camera is None else camera
    return camera.transform_points_screen(verts, R, T, image_size)[..., :2]


def transfer_keypoints(
    src_keypoints: torch.Tensor,
    src_verts_2d: torch.Tensor,
    src_visible: torch.Tensor,
    tgt_verts_2d: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Transfer 2D keypoints from source to target images through the nearest visible projected source vertex.

    Args:
        src_keypoints: (P, K, 2) source keypoints (column, row) in pixels.
        src_verts_2d: (P, V, 2) projected source vertices, same pixel convention.
        src_visible: (P, V) bool, vertices visible in the source image.
        tgt_verts_2d: (P, V, 2) the same vertices projected in the target images.

    Returns:
        transferred: (P, K, 2) keypoints in the target images (NaN for a source without visible vertices).
        vertex_idx: (P, K) long index of the chosen vertex (-1 for a source without visible vertices).
    """
    dims = check_shape(src_keypoints, "P, K, 2", "src_keypoints")
    P = dims["P"]
    check_shape(src_verts_2d, "P, V, 2", "src_verts_2d", dims)
    check_shape(tgt_verts_2d, "P, V, 2", "tgt_verts_2d", dims)
    check_shape(src_visible, "P, V", "src_visible", dims)
    if src_visible.dtype != torch.bool:
        raise ValueError(f"src_visible must be a bool tensor, got {src_visible.dtype}")
    kp = src_keypoints.to(src_verts_2d)
    d2 = (kp.unsqueeze(2) - src_verts_2d.unsqueeze(1)).square().sum(-1)  # (P, K, V)
    d2 = d2.masked_fill(~src_visible.unsqueeze(1), float("inf"))
    vertex_idx = d2.argmin(dim=-1)  # (P, K)
    transferred = torch.gather(tgt_verts_2d, 1, vertex_idx.unsqueeze(-1).expand(-1, -1, 2))
    none_visible = ~src_visible.any(dim=1)  # (P,)
    if none_visible.any():
        transferred = transferred.masked_fill(none_visible.view(P, 1, 1), float("nan"))
        vertex_idx = vertex_idx.masked_fill(none_visible.view(P, 1), -1)
    return transferred, vertex_idx


def pck(
    pred: torch.Tensor,
    gt: torch.Tensor,
    valid: torch.Tensor,
    thresholds: Sequence[float],
) -> tuple[torch.Tensor, int]:
    """Fraction of valid keypoints within each pixel threshold of the ground truth.

    Args:
        pred: (..., 2) predicted keypoints (NaN counts as wrong).
        gt: (..., 2) ground-truth keypoints.
        valid: (...) bool, which keypoints count.
        thresholds: pixel distances.

    Returns:
        pck: (len(thresholds),) fractions (NaN when nothing is valid); num_valid: the count of valid
            keypoints.

    Example:
        >>> pred = torch.tensor([[0.0, 0.0], [3.0, 4.0]])
        >>> gt = torch.zeros(2, 2)
        >>> pck(pred, gt, torch.tensor([True, True]), [1.0, 5.0])[0].tolist()
        [0.5, 1.0]
    """
    dims = check_shape(pred, "*N, 2", "pred")
    check_shape(gt, "*N, 2", "gt", dims)
    check_shape(valid, "*N", "valid", dims)
    hits, n = _hit_counts(pred, gt, valid, thresholds)
    fractions = hits.to(pred.dtype) / n if n > 0 else torch.full(hits.shape, float("nan"), dtype=pred.dtype)
    return fractions, n


def _hit_counts(
    pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor, thresholds: Sequence[float]
) -> tuple[torch.Tensor, int]:
    err = torch.linalg.vector_norm(pred - gt.to(pred), dim=-1)[valid]
    th = torch.as_tensor(list(thresholds), dtype=err.dtype, device=err.device)
    hits = (err.unsqueeze(0) <= th.unsqueeze(1)).sum(dim=1)  # NaN compares False
    return hits.cpu(), int(valid.sum())


def keypoint_transfer_pck(
    verts: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    vertex_visibility: torch.Tensor,
    keypoints: torch.Tensor,
    image_size: int | tuple[int, int],
    *,
    camera: PerspectiveCamera | None = None,
    alphas: Sequence[float] = (0.05, 0.1, 0.15),
    num_pairs: int = 10000,
    pairs: tuple[np.ndarray | torch.Tensor, np.ndarray | torch.Tensor] | None = None,
    chunk_size: int = 128,
) -> dict[str, float]:
    """PCK by keypoint transfer over image pairs (both directions), UNICORN's CUB protocol.

    Args:
        verts: (N, V, 3) reconstructed meshes of the N test images (shared topology), object frame.
        R: (N, 3, 3) predicted world-to-view rotations.
        T: (N, 3) predicted translations.
        vertex_visibility: (N, V) bool, vertices of faces hit by the hard rasterisation of each image.
        keypoints: (N, K, 3) ground-truth keypoints (column, row, visible) in pixels of the ``image_size``
            frame, pixel centres at integers (the convention of ``transform_points_screen``); visible when >
            0.
        image_size: S or (H, W) of the keypoint frame (256 for CUB); thresholds are ``alpha * max(H, W)``.
        camera: projection, ``PerspectiveCamera(fov=30)`` by default.
        alphas: PCK thresholds as fractions of the image side.
        num_pairs: pairs drawn with :func:`keypoint_pairs` when ``pairs`` is None; when the N images form at most
            ``num_pairs`` ordered pairs (``N (N - 1) <= num_pairs``), every ordered pair is used once instead, which
            gives the exact value the draw estimates.
        pairs: explicit (source, target) index arrays of equal length, instead of drawing them.
        chunk_size: pairs processed at once (memory ~ chunk_size * K * V).

    Returns:
        ``{"pck-5": ..., "pck-10": ..., "pck-15": ...}`` (keys ``pck-{100 alpha}``) and ``"num-valid"``, the
        number of keypoints that counted.
    """
    dims = check_shape(verts, "N, V, 3", "verts")
    N = verts.shape[0]
    check_rotations(R, "R", N)
    check_translations(T, "T", N)
    check_shape(vertex_visibility, "N, V", "vertex_visibility", dims)
    if vertex_visibility.dtype != torch.bool:
        raise ValueError(f"vertex_visibility must be a bool tensor, got {vertex_visibility.dtype}")
    check_shape(keypoints, "N, K, 3", "keypoints", dims)
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}")
    if pairs is None and 1 < N and N * (N - 1) <= num_pairs:
        # each unordered pair once; both directions below make every ordered pair once
        src_idx, tgt_idx = (idx.astype(np.int64) for idx in np.triu_indices(N, k=1))
    elif pairs is None:
        src_idx, tgt_idx = keypoint_pairs(N, num_pairs)
    else:
        src_idx, tgt_idx = (np.asarray(torch.as_tensor(p).cpu(), dtype=np.int64) for p in pairs)
        if src_idx.shape != tgt_idx.shape or src_idx.ndim != 1 or src_idx.size == 0:
            raise ValueError("pairs must be two non-empty 1D index arrays of equal length")
        if min(src_idx.min(), tgt_idx.min()) < 0 or max(src_idx.max(), tgt_idx.max()) >= N:
            raise ValueError(f"pair indices must lie in [0, {N})")
    H, W = image_hw(image_size)
    thresholds = [float(a) * max(H, W) for a in alphas]

    with torch.no_grad():
        proj = project_vertices(verts, R, T, (H, W), camera)  # (N, V, 2)
        kp_xy = keypoints[..., :2].to(proj)
        kp_vis = keypoints[..., 2] > 0
        # both directions: (a -> b) for every pair and its reverse
        src_all = torch.as_tensor(np.concatenate([src_idx, tgt_idx]), device=verts.device)
        tgt_all = torch.as_tensor(np.concatenate([tgt_idx, src_idx]), device=verts.device)
        hits = torch.zeros(len(thresholds), dtype=torch.float64)
        total = 0
        for start in range(0, src_all.numel(), chunk_size):
            s, t = src_all[start : start + chunk_size], tgt_all[start : start + chunk_size]
            transferred, _ = transfer_keypoints(kp_xy[s], proj[s], vertex_visibility[s], proj[t])
            valid = kp_vis[s] & kp_vis[t]
            chunk_hits, n = _hit_counts(transferred, kp_xy[t], valid, thresholds)
            hits += chunk_hits.double()
            total += n
    scores = {f"pck-{round(100 * a)}": (float(h) / total if total > 0 else float("nan")) for a, h in zip(alphas, hits)}
    scores["num-valid"] = float(total)
    return scores
