"""Test-time refinement: fit the network's prediction to each image, keeping the category prior.

A network that predicts in one pass gives what it learnt of the category; refinement starts from its prediction
and optimises, per image, a few variables against the training's 3D-step objective (the reconstruction terms of
:class:`unicorn.objectives.losses.ReconstructionLoss` and the mesh regularisers, built by
:func:`unicorn.objectives.loss_factory.build_losses`, normal consistency and
Laplacian, with the model's weights), plus a penalty on leaving the prediction (the prior). The model's weights
stay frozen (eval mode: BatchNorm uses its running statistics); the encoders run once.

The variables come in parts (:data:`PARTS`):

- ``codes``: the shape, texture and background codes (a delta on each, decoded by the network's own
  generators, so the result stays in what the network can express; masked like the codes);
- ``texture``: a colour offset of the whole texture and a residual of every texel, added to the texture image
  (clamped to [0, 1]); the offset carries a colour correction to the sides the image does not show;
- ``vertices``: per-vertex offsets of the canonical mesh and a log-residual of the anisotropic scale;
- ``pose``: a small rotation (Euler angles about the view axes, radians) and a translation residual.

With ``codes_first`` > 0 the codes move alone for that share of the steps before the residuals join (the
default, 0, moves every part from the first step).

What one view can tell: by default the appearance and the silhouette are refined (the texture and background
codes, the whole texture's colour offset, small vertex offsets held by a strong prior that bring the mesh's
outline onto the image's, so the texture lands on the object's own pixels; the per-texel residual is held close to
zero by a strong prior), and the shape code and the pose keep the network's prediction: fitted to a single view,
they can explain that view at the expense of the others (``docs/reconstruct.md`` has the measurements on views the
refinement never saw, ``benchmarks/refine.py``); ``lr_shape_code`` and the ``pose`` part turn them on.

Backgrounds: a model with a background branch refines its background code with the other codes, so the
background's pixels are explained by the background and the object keeps to its own. A model without one (trained
on ShapeNet-style renderings on white) renders over the renderer's background colour: fitted to a photo with a
background, the object would take the background's colour at its borders and grow into it. Give such a model the
object cut out (a transparent PNG, composited on white by :mod:`unicorn.io.images`).

Each image's variables are independent and the objective is a sum over images, so refining a batch gives the same
result as refining its images one at a time (Adam is element-wise), up to floating-point rounding. Nothing is
drawn at random: a refinement is deterministic on a given device.

Each image gets the iterate of lowest objective among those evaluated (the network's prediction, the state before
every later step and the state after the last), not the last one, so a refinement is never worse than the network's
prediction by its objective. Adam's first step moves every variable with a gradient by about its learning rate,
however small the gradient: on a prediction that already fits its image the per-texel residual's prior
(``texture_weight`` times its mean square) can outweigh what the step gains, and the objective oscillates above
its start for a few steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

import torch
from tqdm.auto import tqdm

from unicorn.checks import is_number
from unicorn.errors import UserError
from unicorn.geometry.rotations import euler_angles_to_matrix
from unicorn.model.autoencoder import Prediction, Unicorn, world_verts
from unicorn.objectives.loss_factory import ImageLosses, build_losses

__all__ = [
    "DEFAULT_PARTS",
    "MAX_STEPS",
    "PARTS",
    "RefineOptionsError",
    "RefineOptions",
    "Refinement",
    "parse_parts",
    "refine",
]

#: the most refinement steps (``RefineOptions.steps``, ``unicorn-reconstruct --refine``): 200 times the usual 50
MAX_STEPS = 10_000


class RefineOptionsError(UserError, ValueError):
    """A refinement setting out of its range (the message names it)."""


#: the refinable parts: name -> what it optimises
PARTS: dict[str, str] = {
    "codes": "the shape, texture and background codes, decoded by the network",
    "texture": "a colour offset of the whole texture and a residual of every texel",
    "vertices": "per-vertex offsets of the canonical mesh and a log-residual of the scale",
    "pose": "a small rotation and a translation residual of the selected pose",
}

#: the parts refined by default (``RefineOptions.parts``, ``--refine-parts default``)
DEFAULT_PARTS = ("codes", "texture", "vertices")


@dataclass(frozen=True)
class RefineOptions:
    """How to refine (defaults: the ones ``unicorn-reconstruct --refine N`` uses).

    How the defaults were chosen, and what they do on views the refinement never saw: ``docs/reconstruct.md``
    (``benchmarks/refine.py``).

    Attributes:
        steps: Adam steps (0: the prediction itself).
        parts: names of :data:`PARTS` to optimise, or one string: ``"default"``, ``"all"`` or names joined by
            commas (``"codes,pose"``; :func:`parse_parts`); kept as a tuple of names.
        codes_first: share of the steps in which only the codes move (when ``codes`` is among the parts); the
            residual parts join after it. 0: everything from the first step.
        lr_codes, lr_texture, lr_vertices, lr_pose: Adam learning rates of each part's variables (codes in code
            units, texture in colour units, vertices and translation in world units, rotation in radians); the
            texture and background codes move at ``lr_codes``.
        lr_shape_code: Adam learning rate of the shape code (part ``codes``; 0: the network's shape is kept).
        code_weight: prior weight on the code deltas, times their squared norm (sum over code dimensions).
        colour_weight: prior weight on the texture's colour offset, times its square (mean over RGB).
        texture_weight: prior weight on the texture's per-texel residual, times its mean square over texels.
        vertex_weight: prior weight on the vertex offsets and the log-scale residual, times their mean square.
        pose_weight: prior weight on the rotation (radians) and translation residuals, times their squared norm.
        progress: show a progress bar over the steps.
    """

    steps: int = 50
    parts: tuple[str, ...] | str = DEFAULT_PARTS
    codes_first: float = 0.0
    lr_codes: float = 0.1
    lr_shape_code: float = 0.0
    lr_texture: float = 0.02
    lr_vertices: float = 0.001
    lr_pose: float = 0.005
    code_weight: float = 0.001
    colour_weight: float = 0.01
    texture_weight: float = 100.0
    vertex_weight: float = 100.0
    pose_weight: float = 0.1
    progress: bool = False

    def __post_init__(self) -> None:
        """Raises :class:`RefineOptionsError` for a value out of its range (``steps`` a whole number in
        [0, :data:`MAX_STEPS`]: ``50.0`` is taken as 50)."""
        if not is_number(self.steps) or not float(self.steps).is_integer():
            raise RefineOptionsError(f"steps must be a whole number, got {self.steps!r}")
        object.__setattr__(self, "steps", int(self.steps))  # frozen: set once, here
        if not 0 <= self.steps <= MAX_STEPS:
            raise RefineOptionsError(f"steps must be in [0, {MAX_STEPS:,}] (refine.MAX_STEPS), got {self.steps:,}")
        object.__setattr__(self, "parts", parse_parts(self.parts))
        if not is_number(self.codes_first) or not 0.0 <= self.codes_first <= 1.0:
            raise RefineOptionsError(f"codes_first must be a number in [0, 1], got {self.codes_first!r}")
        for f in fields(self):
            if f.name.startswith("lr_") or f.name.endswith("_weight"):
                value = getattr(self, f.name)
                if not is_number(value) or value < 0:
                    raise RefineOptionsError(f"{f.name} must be a finite number >= 0, got {value!r}")


def parse_parts(parts: str | Sequence[str]) -> tuple[str, ...]:
    """The part names of ``parts``: a sequence of names of :data:`PARTS`, or one string: ``"default"``
    (:data:`DEFAULT_PARTS`), ``"all"`` (every part) or names joined by commas.

    Raises:
        RefineOptionsError: an unknown part, or no part.
    """
    named = {"default": DEFAULT_PARTS, "all": tuple(PARTS)}
    if isinstance(parts, str):
        parts = named.get(parts) or tuple(q.strip() for q in parts.split(",") if q.strip())
    parts = tuple(parts)
    unknown = [q for q in parts if q not in PARTS]
    if unknown or not parts:
        found = f"unknown refinement part(s) {unknown}" if unknown else "no refinement part"
        raise RefineOptionsError(f"{found}; choose 'default', 'all' or from {list(PARTS)}")
    return parts


@dataclass
class Refinement:
    """The result of :func:`refine` for B images.

    Attributes:
        prediction: the refined :class:`~unicorn.model.Prediction` (codes, mesh, scale, texture, background, R, T;
            ``poses`` keeps the network's candidates and probabilities), detached.
        initial: the network's prediction it started from, detached.
        losses: (steps + 1, B) each image's objective before every step and after the last.
        objective: (B,) each image's objective at ``prediction``: the lowest of its ``losses``.
        best_step: (B,) the row of ``losses`` each image's ``prediction`` comes from: the first of its lowest
            (0: the network's prediction, when no step lowered the objective).
    """

    prediction: Prediction
    initial: Prediction
    losses: torch.Tensor
    objective: torch.Tensor
    best_step: torch.Tensor


class _Variables:
    """Each part's per-image variables (all zero: the prediction itself), on the prediction's device."""

    def __init__(self, model: Unicorn, pred: Prediction, parts: Sequence[str], move_shape: bool = True) -> None:
        B = pred.verts.shape[0]

        def zeros(*shape: int) -> torch.Tensor:
            return pred.verts.new_zeros(B, *shape, requires_grad=True)

        self.groups: dict[str, list[torch.Tensor]] = {}
        self.shape = zeros(pred.shape_code.shape[1])
        self.texture_code = zeros(pred.texture_code.shape[1])
        self.background_code = zeros(pred.background_code.shape[1]) if pred.background_code is not None else None
        self.colour = zeros(pred.texture.shape[1], 1, 1)
        self.texture = zeros(*pred.texture.shape[1:])
        self.offsets = zeros(*pred.canonical_verts.shape[1:])
        self.log_scale = zeros(3)
        self.rotation = zeros(3)
        self.translation = zeros(3)
        self.shape.requires_grad_(move_shape)  # a kept shape: no gradient through the shape network
        codes = [self.shape] if move_shape else []
        codes += [self.texture_code] + ([self.background_code] if self.background_code is not None else [])
        all_groups = {
            "codes": codes,
            "texture": [self.colour, self.texture],
            "vertices": [self.offsets, self.log_scale],
            "pose": [self.rotation, self.translation],
        }
        self.groups = {p: all_groups[p] for p in PARTS if p in parts}


def _decode(model: Unicorn, pred: Prediction, v: _Variables, average_texture: bool) -> Prediction:
    """The prediction moved by the variables (with gradients to them)."""
    z_sh = pred.shape_code + model.shape.mask(v.shape)
    z_tx = pred.texture_code + model.texture.mask(v.texture_code)
    z_bg = None
    if model.background is not None and v.background_code is not None:
        z_bg = pred.background_code + model.background.mask(v.background_code)
    canonical, maps, bkg = model.decode(z_sh, z_tx, z_bg, average_texture)
    canonical = canonical + v.offsets
    scale = pred.scale * v.log_scale.exp()
    maps = (maps + v.colour + v.texture).clamp(0.0, 1.0)
    R = pred.R @ euler_angles_to_matrix(v.rotation, "XYZ")
    return replace(
        pred,
        shape_code=z_sh,
        texture_code=z_tx,
        background_code=z_bg,
        canonical_verts=canonical,
        scale=scale,
        verts=world_verts(canonical, scale),
        texture=maps,
        background=bkg,
        R=R,
        T=pred.T + v.translation,
    )


def _losses(model: Unicorn) -> ImageLosses:
    """The training's 3D-step loss modules for a model's configuration, on its device (built once per refinement)."""
    reconstruction, regularizer = build_losses(model.config["loss"], model.template)
    device = model.template.verts.device
    return ImageLosses(reconstruction.to(device), regularizer.to(device))


def _objective(
    model: Unicorn, fns: ImageLosses, images: torch.Tensor, p: Prediction, v: _Variables, o: RefineOptions
) -> torch.Tensor:
    """Each image's objective (B,): reconstruction terms + mesh regularisers + prior."""
    rec, _ = model.render(p.verts, p.texture, p.R, p.T, p.background)
    terms = fns.reconstruction(rec, images)
    loss = sum(terms.values()) if terms else images.new_zeros(images.shape[0])
    for term in fns.regularizer(p.verts, reduction="none").values():
        loss = loss + term
    codes = [v.shape, v.texture_code] + ([v.background_code] if v.background_code is not None else [])
    prior = o.code_weight * sum(c.square().sum(1) for c in codes)
    prior = prior + o.colour_weight * v.colour.square().flatten(1).mean(1)
    prior = prior + o.texture_weight * v.texture.square().flatten(1).mean(1)
    prior = prior + o.vertex_weight * (v.offsets.square().flatten(1).mean(1) + v.log_scale.square().mean(1))
    prior = prior + o.pose_weight * (v.rotation.square().sum(1) + v.translation.square().sum(1))
    return loss + prior


def _where(better: torch.Tensor, new: Prediction, old: Prediction) -> Prediction:
    """``new``'s images where ``better`` (B,) holds, ``old``'s elsewhere, detached (``poses``: ``old``'s)."""

    def pick(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
        if a is None or b is None:
            return b
        return torch.where(better.view(-1, *[1] * (a.dim() - 1)), a.detach(), b)

    names = [f.name for f in fields(new) if isinstance(getattr(new, f.name), torch.Tensor | None)]
    return replace(old, **{n: pick(getattr(new, n), getattr(old, n)) for n in names})


def _detached(pred: Prediction) -> Prediction:
    return replace(
        pred,
        **{
            f.name: getattr(pred, f.name).detach()
            for f in fields(pred)
            if isinstance(getattr(pred, f.name), torch.Tensor)
        },
    )


def refine(
    model: Unicorn,
    images: torch.Tensor,
    options: RefineOptions | None = None,
    initial: Prediction | None = None,
    average_texture: bool = False,
) -> Refinement:
    """Refine the network's prediction of each image against that image (see the module docstring).

    Args:
        model: the model (its weights are not changed; it runs in eval mode and is put back in its mode).
        images: (B, 3, S, S) in [0, 1], S the model's image size.
        options: :class:`RefineOptions` (defaults when None).
        initial: the network's prediction of ``images`` to start from (computed in eval mode when None).
        average_texture: mean-colour textures (as the prediction was made); the texture residual comes on top.

    Returns:
        :class:`Refinement`: each image's iterate of lowest objective, never above the network's prediction's; with 0
        steps, or none that lowers an image's objective, that image's ``prediction`` is the initial prediction.

    Raises:
        RuntimeError: steps to take under ``torch.inference_mode()``, where no gradient can be computed (under
            ``torch.no_grad()`` the steps compute theirs).
    """
    o = RefineOptions() if options is None else options
    model.check_images(images)
    if o.steps > 0 and torch.is_inference_mode_enabled():
        raise RuntimeError(
            "refine takes gradient steps, which torch.inference_mode() forbids: call it under torch.no_grad() or "
            "outside inference mode"
        )
    if initial is not None and initial.canonical_verts.shape[0] != images.shape[0]:
        raise ValueError(
            f"initial holds {initial.canonical_verts.shape[0]} predictions for {images.shape[0]} images: "
            "give refine the network's prediction of these images"
        )
    was_training = model.training
    # frozen weights: no gradient is computed for them (the variables' are the only ones asked for)
    trainable = [q for q in model.parameters() if q.requires_grad]
    model.eval().requires_grad_(False)
    try:
        with torch.no_grad():
            start = model.predict(images, average_texture) if initial is None else initial
        start = _detached(start)
        v = _Variables(model, start, o.parts, move_shape=o.lr_shape_code > 0)
        fns = _losses(model)
        params = v.groups
        steps = o.steps if params else 0
        lrs = {"codes": o.lr_codes, "texture": o.lr_texture, "vertices": o.lr_vertices, "pose": o.lr_pose}
        groups = [{"params": g, "lr": lrs[p]} for p, g in params.items()]
        if "codes" in params and o.lr_shape_code > 0:  # the shape code at its own rate
            groups = [{"params": [v.shape], "lr": o.lr_shape_code}] + [
                {**grp, "params": [t for t in grp["params"] if t is not v.shape]} for grp in groups
            ]
        opt = torch.optim.Adam(groups) if params else None
        warmup = round(o.codes_first * steps) if "codes" in params else 0
        losses = []
        # each image's iterate of lowest objective so far: its prediction, objective and step
        best, best_loss = start, None
        best_step = torch.zeros(images.shape[0], dtype=torch.long, device=images.device)

        def keep_best(step: int, current: Prediction, loss: torch.Tensor) -> None:
            nonlocal best, best_loss, best_step
            if best_loss is None:  # step 0, all variables zero: the network's prediction itself
                best_loss = loss
                return
            better = loss < best_loss
            best, best_step = _where(better, current, best), torch.where(better, step, best_step)
            best_loss = torch.where(better, loss, best_loss)

        for step in tqdm(range(steps), desc="refine", unit="step", disable=not o.progress, leave=False):
            active = [t for p, g in params.items() if p == "codes" or step >= warmup for t in g]
            with torch.enable_grad():  # callers may be under no_grad (e.g. beside model.predict)
                current = _decode(model, start, v, average_texture)
                loss = _objective(model, fns, images, current, v, o)
                losses.append(loss.detach())
                keep_best(step, current, losses[-1])
                grads = torch.autograd.grad(loss.sum(), active)
            for group in params.values():
                for t in group:
                    t.grad = None
            for t, g in zip(active, grads, strict=True):
                t.grad = g
            opt.step()  # type: ignore[union-attr]  # parameters without a gradient (parts not yet active) are left alone
        with torch.no_grad():
            last = _decode(model, start, v, average_texture) if steps > 0 else start
            losses.append(_objective(model, fns, images, last, v, o))
            keep_best(steps, last, losses[-1])
    finally:
        model.train(was_training)
        for q in trainable:
            q.requires_grad_(True)
    return Refinement(
        prediction=_detached(best),
        initial=start,
        losses=torch.stack(losses),
        objective=best_loss,  # type: ignore[arg-type]  # set at step 0
        best_step=best_step,
    )
