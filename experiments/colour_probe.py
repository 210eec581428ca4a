"""Where does a trained model's colour error come from: the metric, the texture generator, or the encoder?

For views of the synthetic benchmark (the test split, or ``--split train`` for the objects the model was trained
on), the model's predicted shape and pose are kept fixed and the textures are re-fitted per image with the
training's reconstruction loss (Adam, ``--steps``):

- ``amortised``: the model's own textures (what ``unicorn-eval`` scores);
- ``code-opt``: the texture *code* optimised per image, through the model's generator: what the generator can
  express; the gap to ``amortised`` is the encoder's (amortisation);
- ``map-opt``: the texture *image* optimised per image, every texel free: what the loss can reach at this shape
  and pose.

With ``--refit-steps N``, a fourth row, ``regressor-refit``: the texture code regressor (encoder features -> code)
trained again from the model's weights for N Adam steps, alone, with the reconstruction loss on training views at the
model's own shapes and poses (encoder and generator fixed), then scored on the probed views: what the amortised
textures reach when the regressor is optimised for colour alone, on the features the model has. Near ``code-opt``:
the joint training leaves the regression short; near ``amortised``: the features or the regressor's form limit it.

After the table, the spread of the regressed texture codes against the codes fitted per image (``code-opt``): a
regressor that shrinks the codes towards their mean gives textures nearer the category's average colour. Last, a
``readout``: an affine map from the texture branch's encoder features to the ground-truth colour (interiors), fitted
by ridge regression on the training views (its penalty chosen by cross-validation over the training objects), and
scored on the probed views: whether the encoder's features carry the colour of these objects at all (on the
training split the views it was fitted on are among the probed ones); then the same from each stage of that encoder
(its output averaged over the map, as ``model.encoder.pooled`` would take it): where in the network the colour of
new objects is lost.

Each row is scored with the colour ratio (:func:`unicorn.metrics.instance.color_errors`: error of the mean
foreground colour over the error of predicting the views' average colour) on whole masks and on mask interiors
(each mask eroded by one pixel, ``interior=1``, what ``unicorn-eval`` reports).

    python experiments/colour_probe.py outputs/synthetic/runs/<time>/checkpoints/last.ckpt --root <dataset folder>
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch

from unicorn.data import build_dataset
from unicorn.evaluation.rendering import hard_render
from unicorn.io import load_model
from unicorn.metrics import code_spread
from unicorn.metrics.instance import color_errors, mean_foreground_color
from unicorn.model.encoder import STAGES
from unicorn.objectives import ReconstructionLoss

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import existing_file, existing_folder, non_negative_int, positive_float, positive_int  # noqa: E402

FOLDS = 5  # cross-validation folds of the readout's penalty, over the training objects
PENALTIES = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)  # the readout's ridge penalties tried (times the number of views)


def colour_ratios(model, pred, maps: torch.Tensor, images: torch.Tensor, masks: torch.Tensor) -> dict[str, float]:
    """Colour ratio of the textures ``maps`` at the predicted shapes and poses, on whole masks and interiors."""
    with torch.no_grad():
        hard = hard_render(model, pred.verts, maps, pred.R, pred.T, images.shape[-1], 4)
    out = {}
    for name, r in (("whole masks", 0), ("interiors", 1)):
        p = mean_foreground_color(hard.images[:, :3], hard.images[:, 3:], interior=r).double()
        g = mean_foreground_color(images, masks, interior=r).double()
        ok = ~(torch.isnan(p).any(1) | torch.isnan(g).any(1))
        err, base = color_errors(p[ok], g[ok])
        out[name] = float(err.mean() / base.mean())
    return out


def code_shrinkage(regressed: torch.Tensor, fitted: torch.Tensor) -> dict[str, float]:
    """How far the regressed texture codes (N, C) are shrunk against the codes fitted per image (N, C).

    ``regressed`` and ``fitted``: each set's spread (:func:`unicorn.metrics.code_spread` per entry, averaged over the
    entries); ``r2``: the share of the fitted codes' variance that an affine map of the regressed codes explains
    (least squares).
    """
    regressed, fitted = regressed.double(), fitted.double()
    X = _with_offset(regressed)
    residual = X @ torch.linalg.lstsq(X, fitted).solution - fitted
    r2 = 1 - residual.pow(2).sum() / (fitted - fitted.mean(0)).pow(2).sum()
    return {
        "regressed": float(code_spread(regressed).mean()),
        "fitted": float(code_spread(fitted).mean()),
        "r2": float(r2),
    }


def ridge_readout(
    features: torch.Tensor, targets: torch.Tensor, groups: torch.Tensor, penalties: tuple[float, ...] = PENALTIES
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """An affine map from ``features`` (N, F) to ``targets`` (N, 3) by ridge regression on standardised features,
    its penalty (times N) the one of ``penalties`` with the least squared error over ``FOLDS`` folds of the
    ``groups`` (N,) (objects: views of one object are never split between fit and score).

    Returns the weights (F + 1, 3), the features' mean and std (2, F) and the chosen penalty.
    """
    x, y = features.double(), targets.double()
    stats = torch.stack([x.mean(0), x.std(0).clamp(min=1e-6)])

    def fit(a: torch.Tensor, b: torch.Tensor, penalty: float) -> torch.Tensor:
        eye = torch.eye(a.shape[1], dtype=a.dtype)
        eye[-1, -1] = 0  # the offset is not penalised
        return torch.linalg.solve(a.T @ a + penalty * len(a) * eye, a.T @ b)

    X = _design(x, stats)
    fold = torch.remainder(groups, FOLDS)
    errors = []
    for penalty in penalties:
        err = 0.0
        for k in range(FOLDS):
            held = fold == k
            err += float((X[held] @ fit(X[~held], y[~held], penalty) - y[held]).pow(2).sum())
        errors.append(err)
    best = penalties[min(range(len(penalties)), key=errors.__getitem__)]
    return fit(X, y, best), stats, best


def _with_offset(x: torch.Tensor) -> torch.Tensor:
    """``x`` (N, F) with a column of ones appended (N, F + 1): the design matrix of an affine map."""
    return torch.cat([x, torch.ones_like(x[:, :1])], 1)


def _design(features: torch.Tensor, stats: torch.Tensor) -> torch.Tensor:
    """Features (N, F) standardised with ``stats`` (2, F: mean, std), a column of ones appended: (N, F + 1)."""
    return _with_offset((features.double() - stats[0]) / stats[1])


def readout_colours(weights: torch.Tensor, stats: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """The colours (N, 3) that :func:`ridge_readout`'s map gives features (N, F)."""
    return _design(features, stats) @ weights


def views(data, idx: list[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images (N, 3, S, S), masks (N, 1, S, S) at the images' size and object indices (N,) of views ``idx``."""
    batch = torch.utils.data.default_collate([data[i] for i in idx])
    images = batch["image"]
    masks = batch["mask"].float().reshape(len(idx), 1, *batch["mask"].shape[-2:])
    masks = torch.nn.functional.interpolate(masks, size=images.shape[-2:])  # nearest, as unicorn-eval
    return images, masks, batch["model"]


def refit_regressor(model, reconstruction, images: torch.Tensor, features: torch.Tensor, steps: int, lr: float):
    """A copy of the texture code regressor trained ``steps`` Adam steps (batches of 16) on ``images`` (N, 3, S, S)
    and their texture features (N, F) with the reconstruction loss, at the model's predicted shapes and poses;
    everything else fixed."""
    with torch.no_grad():
        preds = [model.predict(x) for x in images.split(64)]
        verts, R, T = (torch.cat([getattr(p, name) for p in preds]) for name in ("verts", "R", "T"))
    regressor = copy.deepcopy(model.texture.regressor).requires_grad_(True)
    opt = torch.optim.Adam(regressor.parameters(), lr=lr)
    g = torch.Generator().manual_seed(2)
    for _ in range(steps):
        b = torch.randint(len(images), (16,), generator=g)
        maps = model.texture(model.texture.mask(regressor(features[b])))
        rec, _ = model.render(verts[b], maps, R[b], T[b], None)
        loss = sum(reconstruction(rec, images[b]).values()).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return regressor.requires_grad_(False)


def readout_ratio(fit_features, fit_colours, objects, features, truth) -> tuple[float, float]:
    """The colour ratio (interiors) of a ridge readout fitted on ``fit_features`` (N, F) -> ``fit_colours`` (N, 3)
    and applied to ``features`` (M, F) against ``truth`` (M, 3), and its penalty."""
    seen = ~torch.isnan(fit_colours).any(1)  # views whose interior is empty have no colour to fit
    weights, stats, penalty = ridge_readout(fit_features[seen], fit_colours[seen], objects[seen])
    ok = ~torch.isnan(truth).any(1)
    err, base = color_errors(readout_colours(weights, stats, features)[ok], truth[ok])
    return float(err.mean() / base.mean()), penalty


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=existing_file)
    p.add_argument(
        "--root", type=existing_folder, required=True, help="the synthetic dataset folder (with metadata.yaml)"
    )
    p.add_argument("--views", type=positive_int, default=96, help="views of the split (a fixed random choice)")
    p.add_argument(
        "--split",
        choices=("train", "test"),
        default="test",
        help="the test objects, or the training objects (a gap between the two is a generalisation gap)",
    )
    p.add_argument("--steps", type=positive_int, default=300, help="Adam steps of each per-image fit")
    p.add_argument("--lr", type=positive_float, default=1e-2)
    p.add_argument("--readout-views", type=positive_int, default=1200, help="training views the readout is fitted on")
    p.add_argument(
        "--refit-steps",
        type=non_negative_int,
        default=0,
        help="Adam steps of the regressor refit on the readout's views (0: none)",
    )
    p.add_argument("--refit-lr", type=positive_float, default=1e-3)
    args = p.parse_args()

    model, _ = load_model(args.checkpoint)
    model.eval().requires_grad_(False)
    size = model.config["image_size"]
    data = build_dataset("synthetic", args.split, args.root, img_size=size, views="all")
    idx = torch.randperm(len(data), generator=torch.Generator().manual_seed(0))[: args.views].tolist()
    images, masks, _ = views(data, idx)
    with torch.no_grad():
        pred = model.predict(images)

    code = pred.texture_code.clone().requires_grad_(True)
    logits = torch.logit(pred.texture.clamp(1e-3, 1 - 1e-3)).requires_grad_(True)
    fits = {"code-opt": (code, lambda: model.texture(code)), "map-opt": (logits, lambda: torch.sigmoid(logits))}
    reconstruction = ReconstructionLoss.from_config(model.config["loss"])
    with torch.no_grad():
        rec, _ = model.render(pred.verts, pred.texture, pred.R, pred.T, None)
        loss = sum(reconstruction(rec, images).values()).mean()
    rows = {"amortised": (colour_ratios(model, pred, pred.texture, images, masks), float(loss))}
    for name, (param, make) in fits.items():
        opt = torch.optim.Adam([param], lr=args.lr)
        for _ in range(args.steps):
            rec, _ = model.render(pred.verts, make(), pred.R, pred.T, None)
            loss = sum(reconstruction(rec, images).values()).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        rows[name] = (colour_ratios(model, pred, make().detach(), images, masks), float(loss.detach()))

    train = (
        data if args.split == "train" else build_dataset("synthetic", "train", args.root, img_size=size, views="all")
    )
    fit_idx = torch.randperm(len(train), generator=torch.Generator().manual_seed(1))[: args.readout_views].tolist()
    fit_images, fit_masks, objects = views(train, fit_idx)
    # the texture branch's encoder features of the readout's training views and of the probed views, and each of
    # its stages averaged (the readouts' inputs; the regressor refit reads the first)
    encoder = model.encoders[model.encoder_index["texture"]]
    with torch.no_grad():
        fit_features = {"features": torch.cat([model.encode(x, ("texture",))["texture"] for x in fit_images.split(64)])}
        features = {"features": model.encode(images, ("texture",))["texture"]}
        fit_stages = [encoder.stage_means(x, STAGES) for x in fit_images.split(64)]
        fit_features |= {name: torch.cat([f[name] for f in fit_stages]) for name in STAGES}
        features |= encoder.stage_means(images, STAGES)
    if args.refit_steps > 0:
        regressor = refit_regressor(
            model, reconstruction, fit_images, fit_features["features"], args.refit_steps, args.refit_lr
        )
        with torch.no_grad():
            maps = model.texture(model.texture.mask(regressor(features["features"])))
            rec, _ = model.render(pred.verts, maps, pred.R, pred.T, None)
            loss = sum(reconstruction(rec, images).values()).mean()
        rows["regressor-refit"] = (colour_ratios(model, pred, maps, images, masks), float(loss))

    print(f"{len(idx)} {args.split} views, {args.steps} Adam steps per fit\n")
    print("| textures | colour ratio, whole masks | colour ratio, interiors | reconstruction loss (last step) |")
    print("|---|---|---|---|")
    for name, (r, loss) in rows.items():
        print(f"| {name} | {r['whole masks']:.3f} | {r['interiors']:.3f} | {loss:.5f} |")
    spread = code_shrinkage(pred.texture_code, code.detach())
    print(
        f"\ntexture code spread (std per entry, mean over entries): regressed {spread['regressed']:.3f}, fitted per "
        f"image {spread['fitted']:.3f}; fitted explained by an affine map of the regressed: R^2 {spread['r2']:.3f}"
    )

    fit_colours = mean_foreground_color(fit_images, fit_masks, interior=1).double()
    truth = mean_foreground_color(images, masks, interior=1).double()
    print(f"readout (-> colour, ridge fitted on {len(fit_idx)} training views), colour ratio, interiors:")
    for name, fitted in fit_features.items():
        ratio, penalty = readout_ratio(fitted, fit_colours, objects, features[name], truth)
        what = "the texture branch's features" if name == "features" else f"{name}, averaged"
        print(f"- {what}: {ratio:.3f} (penalty {penalty:g})")


if __name__ == "__main__":
    main()
