"""Code diagnostics during training: does each branch still see the image?

A code regressor whose hidden ReLUs are all dead outputs its last layer's bias whatever the image, and a code
that does not vary across images makes the model reconstruct the category mean. Both fail silently: the losses
keep falling (the mean shape and colour are a fair first answer). :class:`CodeDiagnostics` measures them every
N iterations on the most recent training images:

- ``code-std`` / ``code-std-min``: the mean and smallest standard deviation across the images of each active
  code dimension (:func:`~unicorn.metrics.code_spread`); ``raw-std``: the same over every dimension of the
  regressor's output before the progressive mask (a masked dimension still shows whether the regressor
  would vary);
- ``alive-last`` (of ``units-last``): hidden units of the regressor's last hidden layer active for at least
  one of the images (:func:`~unicorn.metrics.active_units`); ``alive-frac``: the share over all its hidden
  layers;
- ``active-dims``: the code size the schedule currently uses;
- ``shape/mesh-spread``: how much the deformed templates of the images differ beyond their proportions
  (:func:`~unicorn.metrics.mesh_spread`, in units of their RMS radius): what the shape code does to the meshes,
  whatever its own scale (typical figures: ``docs/training.md``, "Outputs");
- ``pose/share-min``, ``pose/share-max``: the smallest and largest share of the images whose most likely pose
  candidate is each candidate; ``pose/azim-spread``: how much each candidate's azimuth offset varies across the
  images it is chosen for (std over those images divided by the offset's half range, averaged over the
  candidates chosen at least twice; :func:`pose_diagnostics`). Near 0, the pose branch picks one of K fixed
  viewpoints whatever the image, and the views between them come out up to half a candidate's sector wrong;
  ``pose/share-<k>``: the share of the images whose most likely candidate is candidate k; ``pose/azim-bins``: the
  share of twelve 30-degree azimuth bins that the images' selected azimuths reach;
- ``pose/render-acc``, ``pose/render-azim-error``: the pose branch read on renders of the model's own
  reconstructions of the images at azimuths drawn over the azimuth range
  (:func:`unicorn.objectives.viewpoint.viewpoint_check`, the same draws at every check): the share whose most likely
  candidate is the drawn view's, and the median azimuth error (degrees) of that candidate. No ground truth is
  needed: a model that reads viewpoints finds most renders' candidates; ``pose/render-chance`` (1 / K) is what a
  guess scores;
- ``render/overflow-share``: the share of the pixels rendered since the previous check (by the training steps,
  validation and held-out scoring, not by the checks) that had more candidate faces than the renderer's
  ``faces_per_pixel``; the first check that finds any warns once per run (:mod:`unicorn.lit.overflow`).

Each goes to the loggers as ``diagnostics/<branch>/<name>`` and to ``<run>/diagnostics.csv`` (one row per
check, columns ``<branch>/<name>``). A branch *collapses* when its last hidden layer has no active unit (its
code is constant, masked or not), or when its active code dimensions vary, on average, by less than
``spread_tol`` across the images, or (the shape branch) by less than ``shape_spread_ratio`` times the texture
code's spread: a shape code that barely moves while the texture code does means one shape for every image, which
an absolute tolerance near 0 does not catch (the spreads are not judged on the first check after a code size
changed: a newly unmasked dimension starts at 0 and needs a few iterations to move). The callback then emits a
:class:`CollapseWarning` and a log error naming the branch, the step and the numbers, once when it happens (and
again at the end of training if it has not recovered).

Viewpoint learning *collapses* when, from stage 2 on (the first stage's end, when the reference tells its users to
look), the render accuracy stays below ``viewpoint_acc_tol`` or one candidate is the most likely for more than
``share_max_tol`` of the images: the callback then emits a :class:`ViewpointWarning` and a log error with the
numbers and what to try, once when it happens and again at the end of training if it has not recovered.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections import deque
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_only
from torch import nn

from unicorn.config.schema import DiagnosticsConfig
from unicorn.errors import UnicornWarning
from unicorn.evaluation.tables import candidate_shares
from unicorn.lit.heldout import append_csv_row
from unicorn.lit.loggers import log_step
from unicorn.lit.overflow import TrainingOverflow
from unicorn.metrics import active_units, code_spread, mesh_spread
from unicorn.model.config import CODE_BRANCHES
from unicorn.model.pose import PoseOutput
from unicorn.model.ranges import check_ranges
from unicorn.objectives.viewpoint import viewpoint_check
from unicorn.render import OverflowCounter

__all__ = [
    "CodeDiagnostics",
    "CollapseWarning",
    "ViewpointWarning",
    "code_diagnostics",
    "pose_diagnostics",
    "viewpoint_reasons",
]

log = logging.getLogger(__name__)

#: branch -> the branch whose code spread it is compared with (``CodeDiagnostics.shape_spread_ratio``)
SPREAD_REFERENCE = {"shape": "texture"}


#: the azimuth bins of ``pose/azim-bins`` (degrees)
AZIM_BIN = 30.0
#: the seed of the viewpoint check's draws: every check renders the same viewpoints
VIEWPOINT_SEED = 0


class CollapseWarning(UnicornWarning):
    """A code branch no longer depends on the image (dead regressor units or a constant code)."""

    level = logging.ERROR


class ViewpointWarning(UnicornWarning):
    """The pose branch no longer tells viewpoints apart (renders at known views misread, or one candidate for all)."""

    level = logging.ERROR


def pose_diagnostics(poses: PoseOutput, azim_half_range: float) -> dict[str, float]:
    """Candidate shares and azimuth-offset spread of a batch's pose candidates (see the module docstring).

    Args:
        poses: the K candidates of B images (angles (K, B, 3), probs (K, B)).
        azim_half_range: the azimuth offsets' half range in degrees (``PoseHead.R_range[0]``); 0 (a single
            fixed azimuth) gives a spread of 0.

    Returns:
        ``share-min``, ``share-max``, ``azim-spread`` (NaN when no candidate is chosen twice), ``share-<k>`` for
        every candidate and ``azim-bins`` (the share of the :data:`AZIM_BIN`-degree azimuth bins that the selected
        azimuths reach).
    """
    K, B = poses.probs.shape
    best = poses.best
    shares = candidate_shares(best.tolist(), K)
    azim = poses.angles[best, torch.arange(B, device=best.device), 0].double()
    chosen = [azim[best == k] for k in range(K)]
    spreads = [a.std(correction=0) for a in chosen if len(a) >= 2]
    spread = math.nan
    if spreads:
        spread = float(torch.stack(spreads).mean() / azim_half_range) if azim_half_range > 0 else 0.0
    n_bins = round(360.0 / AZIM_BIN)
    bins = torch.floor(torch.remainder(azim, 360.0) / AZIM_BIN).long().clamp(0, n_bins - 1)
    out = {"share-min": min(shares), "share-max": max(shares), "azim-spread": spread}
    out.update({f"share-{k}": share for k, share in enumerate(shares)})
    out["azim-bins"] = len(set(bins.tolist())) / n_bins
    return out


@torch.no_grad()
def code_diagnostics(model: nn.Module, images: torch.Tensor) -> dict[str, dict[str, float]]:
    """Code spread and active hidden units of each code regressor of ``model`` on ``images``.

    The model runs as given (call it in eval mode so that batch-norm statistics are not updated); forward hooks
    read the regressors' hidden activations, nothing in the model changes.

    Args:
        model: a :class:`~unicorn.model.Unicorn`.
        images: (B, 3, S, S) in [0, 1], B >= 2.

    Returns:
        branch -> ``active-dims``, ``code-std``, ``code-std-min`` (NaN without active dimensions), ``raw-std``,
        ``alive-last``, ``units-last`` and ``alive-frac`` (``shape`` also ``mesh-spread``), and ``pose`` ->
        :func:`pose_diagnostics` and :func:`~unicorn.objectives.viewpoint.viewpoint_check` (see the module docstring).
    """
    if images.dim() != 4 or images.shape[0] < 2:
        raise ValueError(f"need a (B, 3, S, S) batch with B >= 2 images, got {tuple(images.shape)}")
    # the code branches' regressors (``background`` only when the model has one)
    heads = {b: getattr(model, b) for b in CODE_BRANCHES if getattr(model, b, None) is not None}
    hidden: dict[str, list[torch.Tensor]] = {b: [] for b in heads}
    raw: dict[str, torch.Tensor] = {}
    handles = []
    for b, head in heads.items():
        for layer in head.regressor:
            if isinstance(layer, nn.ReLU):
                handles.append(layer.register_forward_hook(lambda m, i, out, b=b: hidden[b].append(out.detach())))
        handles.append(head.regressor.register_forward_hook(lambda m, i, out, b=b: raw.__setitem__(b, out.detach())))
    try:
        pred = model.predict(images)
    finally:
        for h in handles:
            h.remove()
    out: dict[str, dict[str, float]] = {}
    for b, head in heads.items():
        active = head.mask.active_dims
        spread = code_spread(raw[b], active)
        layers = [active_units(a.flatten(1)) for a in hidden[b]]
        row = {
            "active-dims": float(active),
            "code-std": float(spread.mean()) if active > 0 else math.nan,
            "code-std-min": float(spread.min()) if active > 0 else math.nan,
            "raw-std": float(code_spread(raw[b]).mean()),
        }
        if layers:
            row["alive-last"] = float(layers[-1].sum())
            row["units-last"] = float(layers[-1].numel())
            row["alive-frac"] = float(torch.cat(layers).double().mean())
        out[b] = row
    out["shape"]["mesh-spread"] = mesh_spread(pred.canonical_verts)
    out["pose"] = pose_diagnostics(pred.poses, float(model.pose.R_range[0]))
    out["pose"].update(viewpoint_check(model, images, torch.Generator().manual_seed(VIEWPOINT_SEED), pred))
    return out


def viewpoint_reasons(stats: dict[str, float], acc_tol: float, share_max_tol: float) -> list[str]:
    """Why the ``pose`` entry of :func:`code_diagnostics` says viewpoint learning collapsed; empty when it did not."""
    reasons = []
    if stats["render-acc"] < acc_tol:
        reasons.append(
            f"on renders of its own reconstructions at known viewpoints the pose branch picks the right candidate "
            f"for {stats['render-acc']:.0%} (tolerance {acc_tol:.0%}, a guess {stats['render-chance']:.0%}; median "
            f"azimuth error {stats['render-azim-error']:.0f} degrees)"
        )
    if stats["share-max"] > share_max_tol:
        reasons.append(f"one candidate is the most likely for {stats['share-max']:.0%} of the images")
    return reasons


def collapse_reasons(
    stats: dict[str, float],
    spread_tol: float,
    judge_spread: bool = True,
    reference: tuple[str, float] | None = None,
    min_ratio: float = 0.0,
) -> list[str]:
    """Why a branch's numbers (one entry of :func:`code_diagnostics`) say it collapsed; empty when it did not.

    ``judge_spread=False`` skips the spread criteria (right after the code size changed). ``reference``:
    ``(branch name, its code-std)``, another branch's spread that this one's must reach ``min_ratio`` times of
    (not judged when that spread is not positive)."""
    reasons = []
    if stats.get("alive-last") == 0:
        reasons.append(
            f"0 of the {int(stats['units-last'])} units of its code regressor's last hidden layer are active for "
            "any image (dead ReLUs: the code is the same for every image, now or once unmasked)"
        )
    if judge_spread and stats["active-dims"] > 0 and not stats["code-std"] >= spread_tol:
        reasons.append(
            f"its {int(stats['active-dims'])} active code dimensions vary by {stats['code-std']:.2g} on average "
            f"(std across images, tolerance {spread_tol:g}): the code ignores the image"
        )
    elif judge_spread and reference is not None and stats["active-dims"] > 0 and reference[1] > 0:
        name, spread = reference
        if not stats["code-std"] >= min_ratio * spread:
            reasons.append(
                f"its {int(stats['active-dims'])} active code dimensions vary by {stats['code-std']:.2g} on average, "
                f"{stats['code-std'] / spread:.2g} of the {name} code's {spread:.2g} (below {min_ratio:g}): the code "
                "hardly depends on the image"
            )
    return reasons


class CodeDiagnostics(L.Callback):
    """Code spread and dead units of the code regressors during training (see the module docstring).

    Args:
        every_n_steps: check period in iterations (also after the last iteration).
        max_images: the most recent training images kept for the check (at least 2 are needed).
        spread_tol: a code whose active dimensions' std across the images is below this on average has collapsed.
        shape_spread_ratio: so has a shape code whose spread is below this fraction of the texture code's
            (:data:`SPREAD_REFERENCE`); 0: no relative check.
        viewpoint_acc_tol: from stage 2 on, viewpoint learning has collapsed when the render accuracy is below
            this (0: not judged).
        share_max_tol: ... or when one candidate is the most likely for more than this share of the images
            (1: not judged).
        filename: the CSV file, relative to the run directory.
    """

    def __init__(
        self,
        every_n_steps: int = DiagnosticsConfig.every_n_steps,
        max_images: int = DiagnosticsConfig.max_images,
        spread_tol: float = DiagnosticsConfig.spread_tol,
        shape_spread_ratio: float = DiagnosticsConfig.shape_spread_ratio,
        viewpoint_acc_tol: float = DiagnosticsConfig.viewpoint_acc_tol,
        share_max_tol: float = DiagnosticsConfig.share_max_tol,
        filename: str = "diagnostics.csv",
    ) -> None:
        check_ranges(locals(), DiagnosticsConfig)
        self.viewpoint_acc_tol, self.share_max_tol = float(viewpoint_acc_tol), float(share_max_tol)
        self.viewpoint_collapsed: list[str] = []  # reasons, while collapsed
        self.every_n_steps, self.max_images, self.spread_tol = int(every_n_steps), int(max_images), float(spread_tol)
        self.shape_spread_ratio = float(shape_spread_ratio)
        self.filename = filename
        self._images: deque[torch.Tensor] = deque(maxlen=self.max_images)
        self.collapsed: dict[str, list[str]] = {}  # branch -> reasons, while collapsed
        self._dims: dict[str, float] = {}  # branch -> active code size at the previous check
        self.history: list[dict[str, float]] = []
        self.overflow = TrainingOverflow()  # the renders of fit, counted in place of the renderer's warning

    def state_dict(self) -> dict[str, Any]:
        """The kept images, the collapse state and the overflow counts, saved in checkpoints so a resumed run
        measures the same."""
        images = torch.stack(list(self._images)).cpu() if self._images else torch.zeros(0)
        return {
            "images": images,
            "dims": dict(self._dims),
            "collapsed": dict(self.collapsed),
            "viewpoint_collapsed": list(self.viewpoint_collapsed),
            "overflow": self.overflow.state_dict(),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._images.clear()
        self._images.extend(state_dict["images"].unbind(0) if state_dict["images"].numel() else [])
        self._dims = dict(state_dict["dims"])
        self.collapsed = {k: list(v) for k, v in state_dict["collapsed"].items()}
        self.viewpoint_collapsed = list(state_dict.get("viewpoint_collapsed", []))  # absent from older checkpoints
        if "overflow" in state_dict:  # absent from older checkpoints
            self.overflow.load_state_dict(state_dict["overflow"])

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.overflow.start(trainer.global_step)  # on every rank: no render warns by itself during fit

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *exception: BaseException) -> None:
        self.overflow.stop()

    on_exception = on_fit_end  # a failed fit stops counting too

    @rank_zero_only
    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        # kept where training runs: a copy to the host at every iteration would wait for the device each time
        self._images.extend(batch["image"].detach()[: self.max_images].clone().unbind(0))
        if trainer.global_step % self.every_n_steps == 0:
            self.check(trainer, pl_module)

    @rank_zero_only
    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.history or self.history[-1]["step"] != trainer.global_step:
            self.check(trainer, pl_module)
        for branch, reasons in self.collapsed.items():
            self._warn(f"at the end of training the {branch} branch is still collapsed: " + "; ".join(reasons))
        if self.viewpoint_collapsed:
            prefix = "at the end of training viewpoint learning is still collapsed: "
            self._warn_viewpoint(prefix, self.viewpoint_collapsed)

    def check(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, float] | None:
        """Measure the current model on the kept images, log, append the CSV row and warn on a new collapse."""
        if len(self._images) < 2:
            return None
        step = int(trainer.global_step)
        overflow_share = self.overflow.share(step)
        images = torch.stack(list(self._images)).to(pl_module.device)
        was_training = pl_module.training
        pl_module.eval()  # batch-norm statistics must not see these images twice
        try:
            devices = [pl_module.device] if pl_module.device.type == "cuda" else []
            with torch.random.fork_rng(devices=devices), OverflowCounter():  # the check's own renders: not counted
                stats = code_diagnostics(pl_module.model, images)
        finally:
            pl_module.train(was_training)
        row: dict[str, float] = {"step": step, "render/overflow-share": overflow_share}
        for branch, values in stats.items():
            row.update({f"{branch}/{k}": v for k, v in values.items()})
        for branch, values in ((b, stats[b]) for b in CODE_BRANCHES if b in stats):
            settled = self._dims.get(branch) == values["active-dims"]
            self._dims[branch] = values["active-dims"]
            other = SPREAD_REFERENCE.get(branch)
            reference = None
            if other in stats and self.shape_spread_ratio > 0 and math.isfinite(stats[other]["code-std"]):
                reference = (other, stats[other]["code-std"])
            reasons = collapse_reasons(
                values, self.spread_tol, judge_spread=settled, reference=reference, min_ratio=self.shape_spread_ratio
            )
            if reasons and branch not in self.collapsed:
                self._warn(f"the {branch} branch collapsed at iteration {step}: " + "; ".join(reasons))
            elif not reasons and branch in self.collapsed:
                log.info("code diagnostics: the %s branch varies with the image again at iteration %d", branch, step)
            if reasons:
                self.collapsed[branch] = reasons
            else:
                self.collapsed.pop(branch, None)
        self._judge_viewpoints(stats["pose"], step, int(getattr(pl_module, "stage", 2)))
        self.history.append(row)
        metrics = {f"diagnostics/{k}": v for k, v in row.items() if k != "step" and math.isfinite(v)}
        for logger in trainer.loggers:
            logger.log_metrics(metrics, step=log_step(step))  # beside the iteration's training values
        append_csv_row(Path(trainer.default_root_dir) / self.filename, row)
        return row

    def _judge_viewpoints(self, stats: dict[str, float], step: int, stage: int) -> None:
        """Warn when viewpoint learning collapses from stage 2 on; log when it recovers."""
        if stage < 2:
            return
        reasons = viewpoint_reasons(stats, self.viewpoint_acc_tol, self.share_max_tol)
        if reasons and not self.viewpoint_collapsed:
            self._warn_viewpoint(f"viewpoint learning collapsed at iteration {step}: ", reasons)
        elif not reasons and self.viewpoint_collapsed:
            log.info("code diagnostics: the pose branch tells viewpoints apart again at iteration %d", step)
        self.viewpoint_collapsed = reasons

    @staticmethod
    def _warn_viewpoint(prefix: str, reasons: list[str]) -> None:
        text = (
            f"VIEWPOINT COLLAPSE: {prefix}{'; '.join(reasons)}. The poses, and the shapes fitted to them, are likely "
            "wrong for many images: relaunching with another seed costs less than finishing this run"
        )
        warnings.warn(text, ViewpointWarning, stacklevel=2)  # the commands log it at ERROR, into train.log too

    @staticmethod
    def _warn(message: str) -> None:
        text = f"CODE COLLAPSE: {message}. The model cannot reconstruct individual objects this way."
        warnings.warn(text, CollapseWarning, stacklevel=2)
