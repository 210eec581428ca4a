"""Pose candidates (rotation, translation, probability) and the anisotropic scale head."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from unicorn.checks import check_shape, is_number
from unicorn.geometry.rotations import azim_elev_roll_to_rotation, rotation_angle_between
from unicorn.model.mlp import MLP
from unicorn.render.precision import full_precision, to_full_precision

__all__ = [
    "PoseHead",
    "PoseOutput",
    "ScaleHead",
    "anchor_angles",
    "mirrored_pose",
    "scale_deviations",
    "translation_ranges",
]


def _numbers(r: Any, count: int) -> list[float] | None:
    """``r`` as ``count`` finite floats, or None where it is not that (a string, None, another length, NaN)."""
    if isinstance(r, str | bytes) or not isinstance(r, Sequence) or len(r) != count:
        return None
    numbers = [x for x in r if is_number(x)]
    return [float(x) for x in numbers] if len(numbers) == count else None


def _pair(r: Sequence[float], name: str) -> tuple[float, float]:
    pair = _numbers(r, 2)
    if pair is None or pair[1] < pair[0]:
        raise ValueError(f"{name} must be (min, max), finite numbers with min <= max, got {r}")
    return pair[0], pair[1]


def _triple(
    r: Sequence[float] | float, name: str, low: float = -math.inf, high: float = math.inf, what: str = ""
) -> tuple[float, float, float]:
    """``r`` (one number or x, y, z) as three finite floats in [``low``, ``high``); ``what`` says why the bounds."""
    triple = _numbers([r] * 3, 3) if isinstance(r, int | float) else _numbers(r, 3)
    if triple is None or not all(low <= x < high for x in triple):
        bounds = "" if (low, high) == (-math.inf, math.inf) else f" in [{low:g}, {high:g})"
        raise ValueError(f"{name} must be a finite number or 3 of them (x, y, z){bounds}{what}, got {r}")
    return triple[0], triple[1], triple[2]


def translation_ranges(
    T_range: Sequence[float] | float, prior_translation: Sequence[float] | float
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The translation's half-range and centre (x, y, z) of :class:`PoseHead` from one number or three each.

    Raises:
        ValueError: not one finite number or three, a negative half-range, or a centre whose z does not exceed the
            half-range's (a translation could put the object behind the camera).
    """
    t_range, t_init = _triple(T_range, "T_range", low=0.0), _triple(prior_translation, "prior_translation")
    if t_init[2] - t_range[2] <= 0:
        raise ValueError(
            f"prior_translation's z ({t_init[2]:g}) must exceed T_range's z ({t_range[2]:g}): every predicted "
            "translation must keep the object in front of the camera"
        )
    return t_range, t_init


def scale_deviations(scale_range: Sequence[float] | float) -> tuple[float, float, float]:
    """The largest deviation of :class:`ScaleHead`'s scales from 1 per axis, from one number or three.

    Raises:
        ValueError: not one finite number or three in [0, 1).
    """
    return _triple(scale_range, "scale_range", 0.0, 1.0, " (scales 1 +- it: a scale must stay > 0)")


def anchor_angles(
    n_elev: int,
    n_azim: int,
    azim_range: Sequence[float],
    elev_range: Sequence[float],
    roll_range: Sequence[float],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor angles and offset half-ranges of the ``n_elev * n_azim`` pose candidates.

    Azimuths are evenly spaced from the start of ``azim_range`` when it covers a full turn (0, 60, ..., 300
    for 6 candidates) and at bin centres otherwise; elevations at bin centres; roll at the centre of its
    range.
    Each offset is bounded by ``0.52 * range / n`` (0.5 with a single candidate), so neighbouring candidates
    overlap slightly.

    Returns:
        init: (K, 3) anchors (azim, elev, roll) in degrees, elevation-major order.
        half_range: (3,) maximal offsets (azim, elev, roll) in degrees.
    """
    a0, a1 = _pair(azim_range, "azim_range")
    e0, e1 = _pair(elev_range, "elev_range")
    r0, r1 = _pair(roll_range, "roll_range")
    if n_elev < 1 or n_azim < 1:
        raise ValueError(f"need at least one elevation and azimuth, got {n_elev}, {n_azim}")
    da, de = (a1 - a0) / n_azim, (e1 - e0) / n_elev
    full_turn = abs((a1 - a0) - 360.0) < 1e-6
    azims = [a0 + i * da + (0.0 if full_turn else da / 2) for i in range(n_azim)]
    elevs = [e0 + (j + 0.5) * de for j in range(n_elev)]
    roll = (r0 + r1) / 2
    init = torch.tensor([[a, e, roll] for e in elevs for a in azims], dtype=torch.float32)
    ratio = 0.52 if n_elev * n_azim > 1 else 0.5
    half_range = torch.tensor([ratio * da, ratio * de, ratio * (r1 - r0)], dtype=torch.float32)
    return init, half_range


def mirrored_pose(R: torch.Tensor, T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The pose at which an object symmetric through the template's plane z = 0
    (:func:`unicorn.geometry.mesh.mirror_points`) shows the horizontally flipped image of its view at (R, T).

    Flipping the image negates the view's x, ``M_v = diag(-1, 1, 1)``; mirroring the object, ``M_o = diag(1, 1, -1)``,
    leaves a symmetric object as it is, so ``x @ R @ M_v + T @ M_v = (x @ M_o) @ (M_o @ R @ M_v) + T @ M_v``. In
    angles: azimuth ``180 - a``, the same elevation, roll ``-r``; ``tx -> -tx``.

    Args:
        R: (..., 3, 3) rotations (``x_view = x @ R + T``); T: (..., 3) translations.

    Returns:
        ``(M_o @ R @ M_v, T @ M_v)``, of the inputs' shapes.
    """
    # signs by slicing, not by tensors of Python numbers: those are host-to-device copies in a training step
    R = torch.cat([-R[..., :1], R[..., 1:]], dim=-1)  # @ M_v: the first column negated
    R = torch.cat([R[..., :2, :], -R[..., 2:, :]], dim=-2)  # M_o @: the third row negated
    return R, torch.cat([-T[..., :1], T[..., 1:]], dim=-1)


@dataclass
class PoseOutput:
    """All pose candidates, candidate-major (candidate k of sample b at ``[k, b]``).

    Attributes:
        angles: (K, B, 3) azimuth, elevation, roll in degrees.
        R: (K, B, 3, 3) rotations (``x_view = x @ R + T``).
        T: (K, B, 3) translations.
        probs: (K, B) candidate probabilities (softmax over K).
        log_probs: (K, B) their logarithms, from the logits (``probs`` is derived from them).
        logits: (K, B) the probability head's raw outputs (``log_probs`` up to a per-sample constant), or None.
    """

    angles: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    probs: torch.Tensor
    log_probs: torch.Tensor
    logits: torch.Tensor | None = None

    @property
    def best(self) -> torch.Tensor:
        """(B,) index of the most likely candidate."""
        return self.probs.argmax(0)

    def select(self, index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(R (B, 3, 3), T (B, 3))`` of one candidate per sample, the most likely by default."""
        index = self.best if index is None else index
        b = torch.arange(self.R.shape[1], device=self.R.device)
        return self.R[index, b], self.T[index, b]

    def flat(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(R (K*B, 3, 3), T (K*B, 3))``, row ``k * B + b``."""
        K, B = self.probs.shape
        return self.R.reshape(K * B, 3, 3), self.T.reshape(K * B, 3)


class PoseHead(nn.Module):
    """K pose candidates anchored at evenly spaced azimuths, each with bounded offsets and a probability.

    For candidate k: ``angles = tanh(rot_regressors[k](f)) * R_range + R_init`` (azim, elev, roll),
    ``T = tanh(T_regressors[k](f)) * T_range + prior_translation`` and ``p = softmax_k(proba_regressor(f))``.
    The rotation and translation heads are zero-initialised (anchor poses at init), the probability head
    is not. ``angle_ranges`` (3, 2) keeps the (min, max) azimuth, elevation and roll. ``use_translation`` (a
    buffer) holds the translation at its prior during the first stage, and
    ``use_elevation_roll`` (a buffer) each candidate's elevation and roll at its anchor (with one elevation row, the
    middle of their ranges) while ``schedule.curriculum.elevation_roll`` says so.

    Args:
        in_features: encoder feature size (512).
        n_elev, n_azim: candidates = n_elev * n_azim (UNICORN: 1 x 6).
        azim_range, elev_range, roll_range: (min, max) degrees.
        T_range: maximal translation offsets (x, y, z) (0.3 real images, (0.2, 0.2, 0) ShapeNet).
        prior_translation: translation at zero offset ((0, 0, 2.732): the object 2.732 in front).
        n_units, n_layers: MLP width and hidden depth.
    """

    R_init: torch.Tensor
    R_range: torch.Tensor
    angle_ranges: torch.Tensor
    T_range: torch.Tensor
    T_init: torch.Tensor
    use_translation: torch.Tensor
    use_elevation_roll: torch.Tensor

    def __init__(
        self,
        in_features: int = 512,
        n_elev: int = 1,
        n_azim: int = 6,
        azim_range: Sequence[float] = (0.0, 360.0),
        elev_range: Sequence[float] = (-10.0, 30.0),
        roll_range: Sequence[float] = (-30.0, 30.0),
        T_range: Sequence[float] | float = 0.3,
        prior_translation: Sequence[float] = (0.0, 0.0, 2.732),
        n_units: int = 128,
        n_layers: int = 3,
    ) -> None:
        super().__init__()
        init, half_range = anchor_angles(n_elev, n_azim, azim_range, elev_range, roll_range)
        self.n_candidates = init.shape[0]
        # derived from the configuration: kept out of the state dict
        self.register_buffer("R_init", init, persistent=False)
        self.register_buffer("R_range", half_range, persistent=False)
        ranges = [_pair(azim_range, "azim_range"), _pair(elev_range, "elev_range"), _pair(roll_range, "roll_range")]
        self.register_buffer("angle_ranges", torch.tensor(ranges), persistent=False)  # (3, 2): (min, max) degrees
        t_range, t_init = translation_ranges(T_range, prior_translation)
        self.register_buffer("T_range", torch.tensor(t_range), persistent=False)
        self.register_buffer("T_init", torch.tensor(t_init), persistent=False)
        self.register_buffer("use_translation", torch.tensor(True))
        # set by the stage callback every iteration; kept out of the state dict so that checkpoints written
        # without it load unchanged
        self.register_buffer("use_elevation_roll", torch.tensor(True), persistent=False)
        K = self.n_candidates
        self.rot_regressors = nn.ModuleList([MLP(in_features, 3, n_units, n_layers, zero_last=True) for _ in range(K)])
        self.T_regressors = nn.ModuleList([MLP(in_features, 3, n_units, n_layers, zero_last=True) for _ in range(K)])
        self.proba_regressor = MLP(in_features, K, n_units, n_layers)

    def forward(self, features: torch.Tensor) -> PoseOutput:
        """(B, in_features) -> :class:`PoseOutput` with K candidates.

        Under autocast the MLPs run in reduced precision and the candidates (angles, rotations, translations,
        probabilities) are composed from their float32-cast outputs with autocast off: rotations stay orthonormal
        to float32 rounding."""
        check_shape(features, "B, C", "features")
        rot = torch.stack([to_full_precision(mlp(features)) for mlp in self.rot_regressors])  # (K, B, 3)
        trans = torch.stack([to_full_precision(mlp(features)) for mlp in self.T_regressors])  # (K, B, 3)
        logits = to_full_precision(self.proba_regressor(features)).transpose(0, 1)  # (K, B)
        with full_precision(features.device.type):
            return self._compose(rot.tanh(), trans.tanh(), torch.log_softmax(logits, dim=0), logits)

    def _compose(
        self, rot: torch.Tensor, trans: torch.Tensor, log_probs: torch.Tensor, logits: torch.Tensor | None = None
    ) -> PoseOutput:
        """Candidates from offsets in [-1, 1]: rot (K, B, 3), trans (K, B, 3), log_probs (K, B)."""
        tilt = self.use_elevation_roll.to(rot.dtype)
        held = torch.stack([torch.ones_like(tilt), tilt, tilt])  # (3,): azimuth offsets are never held
        angles = rot * (self.R_range * held) + self.R_init.unsqueeze(1)
        R = azim_elev_roll_to_rotation(angles[..., 0], angles[..., 1], angles[..., 2])
        t_off = trans * self.T_range * self.use_translation.to(trans.dtype)
        return PoseOutput(
            angles=angles, R=R, T=t_off + self.T_init, probs=log_probs.exp(), log_probs=log_probs, logits=logits
        )

    def mirror_index(self) -> torch.Tensor:
        """(K,) long: for each candidate, the candidate whose anchor is nearest to its anchor's mirror
        (:func:`mirrored_pose`), the one that should take the horizontally flipped image."""
        angles = self.R_init
        R = azim_elev_roll_to_rotation(angles[:, 0], angles[:, 1], angles[:, 2])  # (K, 3, 3)
        mirrored, _ = mirrored_pose(R, R.new_zeros(R.shape[0], 3))
        return rotation_angle_between(mirrored.unsqueeze(1), R.unsqueeze(0)).argmin(1)

    def anchor_poses(self, batch_size: int, selected: int = 0) -> PoseOutput:
        """The K candidates at their anchors (zero offsets) for ``batch_size`` samples, probability 1 on
        candidate ``selected``: the poses of an untrained head, without its random probabilities."""
        if not 0 <= selected < self.n_candidates:
            raise ValueError(f"selected must be in [0, {self.n_candidates}), got {selected}")
        zeros = self.R_init.new_zeros(self.n_candidates, batch_size, 3)
        log_probs = self.R_init.new_full((self.n_candidates, batch_size), float("-inf"))
        log_probs[selected] = 0.0
        return self._compose(zeros, zeros, log_probs)


class ScaleHead(nn.Module):
    """Anisotropic per-instance scale ``s = tanh(mlp(f)) * scale_range + 1`` (identity at init).

    ``use_scale`` (a buffer) holds ``s = 1`` during the first stage.

    Args:
        in_features: encoder feature size.
        scale_range: maximal deviation per axis (0.3 real images, 0.5 ShapeNet).
        n_units, n_layers: MLP width and hidden depth.
    """

    scale_range: torch.Tensor
    use_scale: torch.Tensor

    def __init__(
        self,
        in_features: int = 512,
        scale_range: Sequence[float] | float = 0.3,
        n_units: int = 128,
        n_layers: int = 3,
    ) -> None:
        super().__init__()
        self.regressor = MLP(in_features, 3, n_units, n_layers, zero_last=True)
        self.register_buffer(
            "scale_range",
            torch.tensor(scale_deviations(scale_range)),
            persistent=False,
        )
        self.register_buffer("use_scale", torch.tensor(True))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(B, in_features) -> (B, 3) scales, float32 at least (under autocast too: they scale every vertex)."""
        offset = torch.tanh(to_full_precision(self.regressor(features))) * self.scale_range
        return 1.0 + offset * self.use_scale.to(offset.dtype)
