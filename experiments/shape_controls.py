"""Controlled runs: can the shape branch express each car, and what keeps it from doing so?

Each row trains the main job's model (``+experiment=synthetic``: tiny model, level-2 template, 32 px cars,
batch 16) with the 3D step only and the ground-truth camera, so that no pose error is involved, with every code
dimension active from the start; one thing changes per row. Rows marked *per-object codes* replace the encoder's
shape code by a free code per training car (an auto-decoder: the deformation field alone, no generalisation),
and are scored on the training cars; the others are scored on the test cars. The last row is no network at all:
each test car's template fitted to the silhouettes of all 24 of its views at their ground-truth cameras
(:func:`unicorn.evaluation.fit_silhouettes`), what these views can say about each shape at this resolution.

Score: shape retrieval (:func:`unicorn.metrics.shape_retrieval`): each reconstruction, posed in its view,
normalised, compared by Chamfer-L1 with every scored car seen in the same view; top-1 / top-3 hits of the right
car, beside chance, and ``detail``, the mean normalised distance between the canonical shapes of two cars
(per-axis normalisation: what varies beyond the anisotropic scale), 0 for one shape for every car; and
``loss-pose`` / ``loss-gap`` (:func:`loss_picks_pose`): whether the reconstruction loss, on the model's own
reconstruction, prefers the right pose to every pose turned more than 30 degrees away: what the pose step could
learn from reconstructions this good.

``--experiment synthetic_wild`` trains the wild mode's model (with its background branch) on its data.

    python experiments/shape_controls.py --rows all --iterations 1200   # about 10 minutes per row on one core
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

from unicorn.cli.errors import one_line
from unicorn.data.synthetic.shapes import CATEGORIES
from unicorn.errors import UserError
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.metrics import sample_points_from_meshes, shape_retrieval, shape_spread
from unicorn.model import (
    Prediction,
    Unicorn,
    world_verts,
)
from unicorn.objectives import NormalConsistencyLoss, ReconstructionLoss, UniformLaplacianLoss

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import positive_float, positive_int, row_numbers, seed_number  # noqa: E402

VIEWS = (0, 6, 12, 18)  # four views per car: side, back quarter, ...
TURN_STEP = 5.0  # degrees of azimuth between the poses loss_picks_pose compares
TURNS = torch.arange(0.0, 360.0, TURN_STEP)  # (A,) the turns of turn_losses, in degrees
NO_CHOICE = {"loss-pose": float("nan"), "loss-gap": float("nan")}  # rows without an encoder's texture


@dataclass(frozen=True)
class Row:
    name: str
    overrides: tuple[str, ...] = ()
    per_object_codes: bool = False
    mean_colour: float = 0.0  # probability of mean-colour textures per batch
    silhouette_fit: bool = False
    extra: dict = field(default_factory=dict)


ROWS = [
    Row("encoder codes"),
    Row("encoder codes, sigma 1e-3", ("renderer.sigma=1e-3",)),
    Row("encoder codes, mean-colour textures p 0.5", mean_colour=0.5),
    Row("per-object codes", per_object_codes=True),
    Row("per-object codes, sigma 1e-3", ("renderer.sigma=1e-3",), per_object_codes=True),
    Row("per-object codes, mean-colour textures", per_object_codes=True, mean_colour=1.0),
    Row("silhouette fit, every view (no network)", silhouette_fit=True),
]


def training_config(overrides: tuple[str, ...], cache: str | None, experiment: str = "synthetic"):  # noqa: ANN201
    """An experiment's training config (the main job's by default) with ``overrides``, validated."""
    import tempfile

    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from unicorn.config import validate
    from unicorn.resources import config_dir

    args = [f"experiment={experiment}", f"paths.output_dir={tempfile.gettempdir()}", *overrides]
    if cache:
        args.append(f"paths.cache_dir={cache}")
    with initialize_config_dir(str(config_dir()), version_base=None):
        return validate(hydra_compose("train", overrides=args))


def compose(overrides: tuple[str, ...], cache: str | None, experiment: str = "synthetic") -> tuple[dict, str]:
    """An experiment's model config (the main job's by default) with ``overrides`` and its synthetic dataset
    folder."""
    from unicorn.config import model_config
    from unicorn.data import prepare_dataset

    cfg = training_config(overrides, cache, experiment)
    d = cfg.dataset
    return model_config(cfg), str(prepare_dataset("synthetic", d.root, d.categories, dict(d.synthetic)))


def scored_views(root: str, split: str, size: int, category: str) -> dict[str, torch.Tensor]:
    """Four views of every car of a split: images, cameras, object ids and ground-truth points."""
    from unicorn.data import build_dataset

    ds = build_dataset("synthetic", split, root, size, category, views="all", with_points=True)
    n = len(ds.models)
    items = [ds[v * n + m] for m in range(n) for v in VIEWS]
    g = torch.Generator().manual_seed(0)
    points = [ds.load_points(m)[0] for m in range(n)]
    return {
        "image": torch.stack([i["image"] for i in items]),
        "R": torch.stack([i["R"] for i in items]),
        "T": torch.stack([i["T"] for i in items]),
        "object": torch.stack([i["model"] for i in items]),
        "candidates": torch.stack([p[torch.randperm(len(p), generator=g)[:2000]] for p in points]),
    }


def score(verts: torch.Tensor, canonical: torch.Tensor, faces: torch.Tensor, views: dict) -> dict[str, float]:
    """Retrieval of object-frame meshes (Q, V, 3) shown at the views' ground-truth cameras."""
    points = sample_points_from_meshes(verts, faces, 2000, seed=0)[0]
    posed = points @ views["R"] + views["T"][:, None]
    hits = shape_retrieval(posed, views["R"], views["candidates"], views["object"])
    canon_points = sample_points_from_meshes(canonical, faces, 2000, seed=0)[0]
    C = views["candidates"].shape[0]
    return {
        "top-1": float(hits["top1"].mean()),
        "top-3": float(hits["top3"].mean()),
        "chance top-3": min(3, C) / C,
        "detail": shape_spread(canon_points, views["object"], per_axis=True),
    }


def turn_losses(
    model: Unicorn,
    pred: Prediction,
    images: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    reconstruction: ReconstructionLoss,
) -> torch.Tensor:
    """(N, A) reconstruction losses of each image's reconstruction turned about the object's vertical axis.

    The reconstruction (mesh, texture and background predicted from the image, ``pred``) is rendered at the
    view's camera ``R`` (N, 3, 3), ``T`` (N, 3) turned by each of the ``A`` azimuths of ``TURNS`` and scored
    against the image (N, 3, S, S) with the training's reconstruction loss.
    """
    turn = azim_elev_roll_to_rotation(TURNS, torch.zeros_like(TURNS))  # (A, 3, 3), x @ turn @ R
    verts, A, losses = pred.verts, len(TURNS), []
    for q in range(len(images)):
        background = None if pred.background is None else pred.background[q].expand(A, -1, -1, -1)
        maps = pred.texture[q].expand(A, -1, -1, -1)
        rec, _ = model.render(verts[q].expand(A, -1, -1), maps, turn @ R[q], T[q].expand(A, -1), background)
        losses.append(sum(reconstruction(rec, images[q].expand(A, -1, -1, -1)).values()))
    return torch.stack(losses)


def loss_picks_pose(losses: torch.Tensor) -> dict[str, float]:
    """Does the reconstruction loss tell each view's pose from :func:`turn_losses` (N, A)?

    ``loss-pose``: the share of views for which some turn within 30 degrees reconstructs better than every turn
    beyond (a tie counts as a miss). At the ground-truth camera, what the ``assigned`` pose objective could learn
    from such reconstructions (``experiments/pose_ambiguity.py`` asks the same of the ground-truth objects); at the
    model's own pose, whether its reconstruction tells that pose from the others. ``loss-gap``: the median of the
    lowest loss more than 30 degrees away over the loss at no turn, minus 1 (0 or below: no preference).
    """
    near = torch.minimum(TURNS, 360.0 - TURNS) <= 30.0
    far_best = losses[:, ~near].min(1).values
    hits = losses[:, near].min(1).values < far_best
    return {"loss-pose": float(hits.float().mean()), "loss-gap": float((far_best / losses[:, 0] - 1.0).median())}


def train(row: Row, cfg: dict, root: str, args: argparse.Namespace) -> tuple[Unicorn, torch.nn.Embedding]:
    """The 3D step with ground-truth cameras, every code dimension active."""
    from unicorn.data import build_dataset

    torch.manual_seed(args.seed)
    data = build_dataset("synthetic", "train", root, cfg["image_size"], args.category)
    model = Unicorn(cfg)
    model.set_active_dims(shape=model.shape.code_dim, texture=model.texture.mask.code_dim)
    model.set_stage_switches(translation=False, deformation=True, scale=True)
    codes = torch.nn.Embedding(len(data.models), model.shape.code_dim)
    torch.nn.init.normal_(codes.weight, std=0.01)
    groups = [{"params": list(model.parameters())}]
    if row.per_object_codes:
        groups.append({"params": list(codes.parameters()), "lr": args.lr * 10})
    opt = torch.optim.Adam(groups, lr=args.lr)
    loader = torch.utils.data.DataLoader(
        data, batch_size=16, shuffle=True, drop_last=True, generator=torch.Generator().manual_seed(args.seed)
    )
    loss_cfg = model.config["loss"]
    reconstruction = ReconstructionLoss.from_config(loss_cfg)
    normal_loss = NormalConsistencyLoss(model.template.faces)
    laplacian_loss = UniformLaplacianLoss(model.template.faces, model.template.num_verts)
    it = 0
    while it < args.iterations:
        for batch in loader:
            images = batch["image"]
            feats = model.encode(images, model.branches())
            average = bool(torch.rand(()) < row.mean_colour)
            p = model.predict_3d(feats, average)
            canonical = model.deform(codes(batch["model"])) if row.per_object_codes else p.canonical_verts
            verts = world_verts(canonical, p.scale)
            rec, _ = model.render(verts, p.texture, batch["R"], batch["T"], p.background)
            loss = sum(v.mean() for v in reconstruction(rec, images).values())
            loss = loss + loss_cfg["normal_weight"] * normal_loss(verts)
            loss = loss + loss_cfg["laplacian_weight"] * laplacian_loss(verts)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            it += 1
            if it >= args.iterations:
                break
    return model.eval(), codes


@torch.no_grad()
def run(row: Row, args: argparse.Namespace) -> dict[str, float]:
    overrides = (*row.overrides, *args.override, f"dataset.categories={args.category}")
    cfg, root = compose(overrides, args.cache, args.experiment)
    start = time.perf_counter()
    if row.silhouette_fit:
        from unicorn.data import build_dataset
        from unicorn.evaluation import fit_silhouettes

        model = Unicorn(cfg).eval()
        views = scored_views(root, "test", cfg["image_size"], args.category)
        ds = build_dataset("synthetic", "test", root, cfg["image_size"], args.category, views="all")
        n = len(ds.models)
        fitted = []
        for m in range(n):
            items = [ds[v * n + m] for v in range(ds.n_views)]
            masks, R, T = (torch.stack([i[k] for i in items]) for k in ("mask", "R", "T"))
            with torch.enable_grad():
                fitted.append(fit_silhouettes(model, masks, R, T, iterations=args.fit_iterations)[0])
        verts = torch.stack(fitted)[views["object"]]
        return {**score(verts, verts, model.template.faces, views), **NO_CHOICE, "minutes": _minutes(start)}
    with torch.enable_grad():
        model, codes = train(row, cfg, root, args)
    views = scored_views(root, "train" if row.per_object_codes else "test", cfg["image_size"], args.category)
    pred = model.predict(views["image"])
    canonical = pred.canonical_verts
    if row.per_object_codes:
        canonical = model.template.verts + model.shape(model.template.verts, codes(views["object"]))
    verts = canonical * pred.scale.unsqueeze(1)
    choice = NO_CHOICE
    if not row.per_object_codes:
        loss = ReconstructionLoss.from_config(model.config["loss"])
        choice = loss_picks_pose(turn_losses(model, pred, views["image"], views["R"], views["T"], loss))
    return {**score(verts, canonical, model.template.faces, views), **choice, "minutes": _minutes(start)}


def _minutes(start: float) -> float:
    return (time.perf_counter() - start) / 60


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iterations", type=positive_int, default=1200, help="training iterations of each row")
    p.add_argument("--fit-iterations", type=positive_int, default=300, help="silhouette-fit Adam steps per car")
    p.add_argument("--lr", type=positive_float, default=2e-4, help="Adam learning rate")
    p.add_argument("--seed", type=seed_number, default=0)
    p.add_argument("--category", default="car", choices=tuple(CATEGORIES), help="synthetic category")
    p.add_argument("--override", action="append", default=[], help="a config override for every row (repeatable)")
    p.add_argument(
        "--rows",
        type=row_numbers(len(ROWS)),
        default="all",
        help=f"comma-separated row numbers (0 to {len(ROWS) - 1}) or 'all'",
    )
    p.add_argument("--cache", help="synthetic dataset cache folder (default: the config's)")
    p.add_argument(
        "--experiment",
        default="synthetic",
        help="the experiment whose model and data the rows use (e.g. synthetic_wild)",
    )
    args = p.parse_args()
    try:  # the experiment and the overrides, before any work
        training_config((*args.override, f"dataset.categories={args.category}"), args.cache, args.experiment)
    except (HydraException, OmegaConfBaseException, UserError) as err:
        message = one_line(err).split(" Config search path:")[0]  # Hydra's list of folders says nothing here
        p.error(f"--experiment / --override: {message}")
    chosen = ROWS if args.rows == "all" else [ROWS[i] for i in args.rows]
    results = {}
    for row in chosen:
        results[row.name] = run(row, args)
        print(row.name, {k: round(v, 3) for k, v in results[row.name].items()}, flush=True)
    cols = list(next(iter(results.values())))
    extra = f", overrides {' '.join(args.override)}" if args.override else ""
    setting = f"{args.iterations} iterations (3D step, ground-truth cameras), Adam lr {args.lr}, seed {args.seed}"
    print(f"\n{setting}{extra}\n")
    print("| control | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for name, row in results.items():
        print(f"| {name} | " + " | ".join(f"{row[c]:.3f}" for c in cols) + " |")


if __name__ == "__main__":
    main()
