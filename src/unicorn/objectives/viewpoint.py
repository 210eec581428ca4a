"""Viewpoint self-supervision: the pose branch learns from the model's own reconstructions rendered at known views.

On images with backgrounds and views from all around, the reconstruction loss alone hardly tells a view from the
one turned round: a per-image texture and background repaint a wrong pose almost as well as the right one. The
renders of the model's own meshes break that tie with a signal no per-image code can absorb: a reconstruction
(shape, scale and texture of a batch image, or a blend of two) is rendered at a viewpoint drawn from the pose
ranges, over the background predicted for another image, and the pose branch must say where the camera was. The
candidate probabilities learn the candidate whose sector holds the drawn view (cross-entropy), and that candidate's
angles and translation regress the drawn ones (SMR's interpolated cycle, SSV's generated-view training).

- :func:`draw_views`: viewpoints drawn uniformly over a :class:`~unicorn.model.pose.PoseHead`'s ranges, each with
  the candidate whose sector holds it (:func:`candidate_of`);
- :func:`render_views`: the reconstructions (blended in pairs for a share of them) rendered at those views;
- :func:`viewpoint_terms`: the cross-entropy, the regression, and the accuracy on the renders;
- :func:`viewpoint_check`: the accuracy on renders of a batch's reconstructions, without training: the health
  signal of training's diagnostics, whatever the pose objective;
- :class:`RenderedViewpoints` (registered as ``"renders"``, ``loss.viewpoint``): the pose step's extra terms.

The pose step renders with detached reconstructions (no gradient reaches the 3D branches through the renders); the
gradients reach the pose heads and the encoder that feeds them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import torch

from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.hostsync import draw_device
from unicorn.model.config import LOSS_KEYS
from unicorn.model.pose import PoseHead, PoseOutput
from unicorn.registry import Registry

if TYPE_CHECKING:
    from unicorn.model.autoencoder import Prediction3D, Unicorn

__all__ = [
    "DrawnViews",
    "RenderedViewpoints",
    "ViewpointSupervision",
    "build_viewpoint_supervision",
    "candidate_of",
    "draw_views",
    "list_viewpoint_supervisions",
    "register_viewpoint_supervision",
    "render_views",
    "viewpoint_check",
    "viewpoint_terms",
    "wrap_degrees",
]


def wrap_degrees(angle: torch.Tensor) -> torch.Tensor:
    """Angles (...,) in degrees wrapped to ``[-180, 180)``."""
    return torch.remainder(angle + 180.0, 360.0) - 180.0


@dataclass
class DrawnViews:
    """Viewpoints drawn for B renders.

    Attributes:
        angles: (B, 3) azimuth, elevation, roll in degrees.
        R: (B, 3, 3) rotations (``x_view = x @ R + T``).
        T: (B, 3) translations.
        candidate: (B,) the candidate whose sector holds each view (:func:`candidate_of`).
    """

    angles: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    candidate: torch.Tensor


def candidate_of(head: PoseHead, angles: torch.Tensor) -> torch.Tensor:
    """The candidate whose sector holds each view: the nearest anchor, azimuth wrapped round, each angle in units of
    its offset half range (angles whose range is a point are left out).

    Args:
        head: the pose head (anchors ``R_init`` (K, 3), half ranges ``R_range`` (3,)).
        angles: (B, 3) azimuth, elevation, roll in degrees.

    Returns:
        (B,) candidate indices.
    """
    diff = angles.unsqueeze(1) - head.R_init.to(angles.dtype)  # (B, K, 3)
    diff = torch.cat([wrap_degrees(diff[..., :1]), diff[..., 1:2]], -1)  # roll: every candidate shares its anchor
    half = head.R_range[:2].to(angles.dtype)
    scaled = torch.where(half > 0, diff / half.clamp_min(1e-12), torch.zeros_like(diff))
    return scaled.square().sum(-1).argmin(1)


def draw_views(
    head: PoseHead, batch_size: int, generator: torch.Generator | None = None, azimuth_only: bool = False
) -> DrawnViews:
    """Viewpoints drawn uniformly over the head's azimuth, elevation and roll ranges and its translation offsets.

    What the head cannot express yet is drawn as the head holds it: the elevation and roll at the candidate's
    anchor while ``use_elevation_roll`` is off, the translation at its prior while ``use_translation`` is off.

    Args:
        head: the pose head whose ranges and switches the views follow.
        batch_size: B.
        generator: the generator of the draws (:func:`~unicorn.hostsync.draw_device`; None: torch's global one on
            the head's device).
        azimuth_only: draw the azimuth alone, the elevation and roll at the candidate's anchor and the translation
            at its prior, whatever the head's switches.

    Returns:
        :class:`DrawnViews` on the head's device.
    """
    device, dtype = head.R_init.device, head.R_init.dtype
    u = torch.rand(batch_size, 6, generator=generator, device=draw_device(device, generator)).to(device, dtype)
    low, high = head.angle_ranges[:, 0], head.angle_ranges[:, 1]
    angles = low + u[:, :3] * (high - low)
    candidate = candidate_of(head, angles)
    held = ~head.use_elevation_roll | azimuth_only
    angles = torch.cat([angles[:, :1], torch.where(held, head.R_init[candidate, 1:], angles[:, 1:])], 1)
    moves = head.use_translation & (not azimuth_only)
    offsets = (2 * u[:, 3:] - 1) * head.T_range * moves.to(dtype)
    R = azim_elev_roll_to_rotation(angles[:, 0], angles[:, 1], angles[:, 2])
    return DrawnViews(angles=angles, R=R, T=head.T_init + offsets, candidate=candidate)


@torch.no_grad()
def render_views(
    model: Unicorn,
    pred: Prediction3D,
    views: DrawnViews,
    mix: float = 0.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Render a batch's reconstructions at drawn views, each over the background predicted for the next image.

    For a share ``mix`` of the renders the shape, scale and texture are blended with those of the next image of the
    batch (weight drawn uniformly in [0, 1]), so the renders are not only the batch's own objects.

    Args:
        model: the :class:`~unicorn.model.Unicorn` that renders.
        pred: its 3D prediction for B images (:meth:`Unicorn.predict_3d`).
        views: B drawn views (:func:`draw_views`).
        mix: share of blended reconstructions, in [0, 1].
        generator: the generator of the blends (:func:`~unicorn.hostsync.draw_device`; None: torch's global one on
            the reconstructions' device).

    Returns:
        (B, 3, S, S) renders in [0, 1], without gradient.
    """
    B = pred.canonical_verts.shape[0]
    on = draw_device(pred.canonical_verts.device, generator)
    u = torch.rand(B, 2, generator=generator, device=on).to(pred.canonical_verts)
    alpha = torch.where(u[:, 0] < mix, u[:, 1], torch.zeros_like(u[:, 1]))  # (B,): 0 keeps the image's own

    def blend(x: torch.Tensor) -> torch.Tensor:
        a = alpha.view(-1, *([1] * (x.dim() - 1)))
        return (1 - a) * x + a * x.roll(-1, 0)

    verts = blend(pred.canonical_verts) * blend(pred.scale).unsqueeze(1)
    background = None if pred.background is None else pred.background.roll(1, 0)
    rgb, _ = model.render(verts, blend(pred.texture), views.R, views.T, background)
    return rgb.clamp(0, 1)


def viewpoint_terms(poses: PoseOutput, views: DrawnViews, head: PoseHead) -> dict[str, torch.Tensor]:
    """How well the pose branch recovers drawn views from their renders.

    Args:
        poses: the K candidates predicted from the B renders.
        views: the views they were rendered at.
        head: the pose head (offset half ranges and switches).

    Returns:
        ``ce``: ``mean_b -log p[k(b), b]`` toward the candidate whose sector holds the view; ``regression``: that
        candidate's squared errors in azimuth (wrapped), elevation and roll (while the head moves them) and
        translation (while it moves it), each in units of its half range, averaged over the batch; ``accuracy``:
        the share of renders whose most likely candidate is that one; ``azim-error``: the median absolute
        azimuth error of the most likely candidate, degrees. Only ``ce`` and ``regression`` carry gradients.
    """
    k, b = views.candidate, torch.arange(views.candidate.shape[0], device=views.candidate.device)
    ce = -poses.log_probs[k, b].mean()
    diff = poses.angles[k, b] - views.angles
    diff = torch.cat([wrap_degrees(diff[:, :1]), diff[:, 1:]], 1)
    moved = torch.stack([torch.ones_like(head.use_elevation_roll), head.use_elevation_roll, head.use_elevation_roll])
    half = head.R_range.clamp_min(1e-6)
    rotation = ((diff / half).square() * moved.to(diff.dtype)).sum(1)
    translation = (((poses.T[k, b] - views.T) / head.T_range.clamp_min(1e-6)).square()).sum(1)
    regression = (rotation + translation * head.use_translation.to(diff.dtype)).mean()
    best = poses.best
    with torch.no_grad():
        accuracy = (best == k).to(diff.dtype).mean()
        azim = poses.angles[best, b, 0]
        azim_error = wrap_degrees(azim - views.angles[:, 0]).abs().quantile(0.5)  # the middle two's mean for even B
    return {"ce": ce, "regression": regression, "accuracy": accuracy, "azim-error": azim_error}


@torch.no_grad()
def viewpoint_check(
    model: Unicorn,
    images: torch.Tensor,
    generator: torch.Generator | None = None,
    pred: Prediction3D | None = None,
) -> dict[str, float]:
    """The pose branch's accuracy on renders of the model's reconstructions of ``images`` at drawn azimuths (each
    at its candidate's anchor elevation and roll and the prior translation: the azimuth is what the candidates split).

    A model whose pose branch reads viewpoints finds the candidate of most renders; one whose viewpoints have
    collapsed (one candidate for every view, or each view's turned-round twin) scores near ``1 / K`` or lower.
    The model runs as given (call it in eval mode so that batch-norm statistics are not updated).

    Args:
        model: a :class:`~unicorn.model.Unicorn`.
        images: (B, 3, S, S) in [0, 1].
        generator: a CPU generator for the views (None: torch's global one).
        pred: the model's prediction for ``images`` when the caller has it (a :class:`~unicorn.model.Prediction`
            serves too); None: predicted here.

    Returns:
        ``render-acc`` (share of renders whose most likely candidate holds their view), ``render-azim-error``
        (median absolute azimuth error in degrees of the most likely candidate) and ``render-chance`` (1 / K).
    """
    model.check_images(images)
    if pred is None:
        pred = model.predict_3d(model.encode(images, model.branches()))
    views = draw_views(model.pose, images.shape[0], generator, azimuth_only=True)
    renders = render_views(model, pred, views)
    poses = model.pose(model.encode(renders, ("pose",))["pose"])
    terms = viewpoint_terms(poses, views, model.pose)
    return {
        "render-acc": float(terms["accuracy"]),
        "render-azim-error": float(terms["azim-error"]),
        "render-chance": 1.0 / model.n_candidates,
    }


class ViewpointSupervision(Protocol):
    """Extra pose-step terms from views whose answer is known (``loss.viewpoint``).

    ``active(iteration)`` says whether a pose step at that iteration adds them; the call takes the model, its
    detached 3D prediction for the batch and returns ``(terms, stats)``: weighted scalar terms that join the pose
    step's total, and detached figures to log.
    """

    def active(self, iteration: int | None) -> bool: ...

    def __call__(
        self, model: Unicorn, pred: Prediction3D
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]: ...


_SUPERVISIONS: Registry[ViewpointSupervision] = Registry("viewpoint supervision", key="viewpoint", methods=("active",))


def register_viewpoint_supervision(name: str, *, overwrite: bool = False) -> Callable[[type], type]:
    """Class decorator: make a viewpoint supervision available as ``loss.viewpoint=name``; its constructor receives
    the options of the ``loss`` group it names."""
    return _SUPERVISIONS.register(name, overwrite=overwrite)


def list_viewpoint_supervisions() -> list[str]:
    """The registered viewpoint-supervision names, sorted."""
    return _SUPERVISIONS.names()


def build_viewpoint_supervision(name: str, **options: Any) -> ViewpointSupervision:
    """The viewpoint supervision registered as ``name``, built from the options its constructor names; the other
    keys of the ``loss`` group (:data:`~unicorn.model.config.LOSS_KEYS`) are left out.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones listed).
        unicorn.registry.UnknownOptionError: an option that is neither the constructor's nor a ``loss`` key.
    """
    return _SUPERVISIONS.build(name, options, group_keys=LOSS_KEYS)


@register_viewpoint_supervision("renders")
class RenderedViewpoints:
    """The batch's reconstructions rendered at drawn views; the pose branch learns the views (module docstring).

    Terms: ``viewpoint`` (``viewpoint_weight`` x the cross-entropy toward each view's candidate) and
    ``viewpoint_pose`` (``viewpoint_pose_weight`` x the candidate's angle and translation regression). Stats:
    ``viewpoint_accuracy`` and ``viewpoint_azim_error`` on the renders.

    Args:
        viewpoint_weight: weight of the candidate cross-entropy.
        viewpoint_pose_weight: weight of the regression of the drawn angles and translation.
        viewpoint_start: the first iteration whose pose steps add the terms.
        viewpoint_every: add them at every n-th pose step from ``viewpoint_start`` (pose and 3D steps alternating
            every iteration: the iterations with ``(iteration - start) // 2`` a multiple of n).
        viewpoint_mix: share of renders that blend two images' reconstructions.
        viewpoint_azimuth_only: draw only the azimuth (elevation and roll at the candidate's anchor, translation at
            its prior; :func:`draw_views`); false: every angle and the translation over their ranges.
    """

    def __init__(
        self,
        viewpoint_weight: float = 0.1,
        viewpoint_pose_weight: float = 0.1,
        viewpoint_start: int = 0,
        viewpoint_every: int = 1,
        viewpoint_mix: float = 0.5,
        viewpoint_azimuth_only: bool = False,
    ) -> None:
        if viewpoint_every < 1 or viewpoint_start < 0 or not 0.0 <= viewpoint_mix <= 1.0:
            raise ValueError(
                "viewpoint_every must be >= 1, viewpoint_start >= 0 and viewpoint_mix in [0, 1], got "
                f"{viewpoint_every}, {viewpoint_start}, {viewpoint_mix}"
            )
        self.weight, self.pose_weight = float(viewpoint_weight), float(viewpoint_pose_weight)
        self.start, self.every, self.mix = int(viewpoint_start), int(viewpoint_every), float(viewpoint_mix)
        self.azimuth_only = bool(viewpoint_azimuth_only)

    def active(self, iteration: int | None) -> bool:
        """Whether the pose step of ``iteration`` adds the terms (None: an iteration-less call, always)."""
        if iteration is None:
            return True
        # pose steps fall on every other iteration: count them, not iterations
        return iteration >= self.start and ((iteration - self.start) // 2) % self.every == 0

    def __call__(self, model: Unicorn, pred: Prediction3D) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        views = draw_views(model.pose, pred.canonical_verts.shape[0], azimuth_only=self.azimuth_only)
        renders = render_views(model, pred, views, self.mix)
        poses = model.pose(model.encode(renders, ("pose",))["pose"])
        t = viewpoint_terms(poses, views, model.pose)
        terms = {"viewpoint": self.weight * t["ce"], "viewpoint_pose": self.pose_weight * t["regression"]}
        return terms, {"viewpoint_accuracy": t["accuracy"], "viewpoint_azim_error": t["azim-error"]}
