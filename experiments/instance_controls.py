"""Controlled experiments: which part of training keeps the model from reconstructing instances?

Each row trains the main job's model (``experiment=synthetic``: tiny model, 32 px cars, batch 16) for the same
number of iterations with one thing controlled, then scores 64 held-out test views:

- ``texture, GT pose``: the 3D step only, with the ground-truth camera, the plain template (no deformation), the
  texture code at its full size from the start: can the texture branch carry each car's colours at all?
- ``texture, GT pose, 2-dim code``: the same with the first stage's 2-dimensional texture code.
- ``3D, GT pose``: shape (full code), scale and texture, the 3D step only, ground-truth camera.
- ``3D, GT pose, + pose steps (shared Adam)``: the same 3D step alternating with the model's own pose step, which
  trains the shared encoder too; one Adam over everything (the paper's).
- ``... (Adam per step)``: the same with one Adam per step kind (``optim.adam_state=per_step``).

Columns: ``colour ratio`` (the reconstructions' mean foreground colour error over the error of predicting the
views' average colour for every view: below 1 only with instance colours; 0 is perfect), ``mask IoU`` (rendered
against ground-truth silhouettes), ``texture code std`` and ``shape code std`` (spread across the views, mean over
the active dimensions), ``shape units alive`` (hidden units of the shape-code regressor's last hidden layer active
for at least one view, of 64).

    python experiments/instance_controls.py --iterations 800     # about 15 minutes on a quiet 2-core CPU
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from unicorn.metrics.instance import active_units, code_spread, color_errors, mean_foreground_color
from unicorn.model import Unicorn
from unicorn.objectives import Objectives

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import positive_float, positive_int, row_numbers, seed_number  # noqa: E402


@dataclass(frozen=True)
class Control:
    name: str
    texture_dims: int = 16
    shape_dims: int = 0
    pose_steps: bool = False
    adam_per_step: bool = False


CONTROLS = [
    Control("texture, GT pose"),
    Control("texture, GT pose, 2-dim code", texture_dims=2),
    Control("3D, GT pose", shape_dims=16),
    Control("3D, GT pose, + pose steps (shared Adam)", shape_dims=16, pose_steps=True),
    Control("3D, GT pose, + pose steps (Adam per step)", shape_dims=16, pose_steps=True, adam_per_step=True),
]


def compose_model_config(cache: str | None) -> tuple[dict, str]:
    """The main job's model config and its synthetic dataset folder."""
    from hydra import compose, initialize_config_dir

    from unicorn.config import model_config, validate
    from unicorn.data import prepare_dataset
    from unicorn.resources import config_dir

    overrides = ["experiment=synthetic", f"paths.output_dir={tempfile.gettempdir()}"]
    if cache:
        overrides.append(f"paths.cache_dir={cache}")
    with initialize_config_dir(str(config_dir()), version_base=None):
        cfg = validate(compose("train", overrides=overrides))
    d = cfg.dataset
    categories = d.categories if d.categories is None or isinstance(d.categories, str) else list(d.categories)
    return model_config(cfg), str(prepare_dataset("synthetic", d.root, categories, dict(d.synthetic)))


def gt_pose_step(model: Unicorn, batch: dict) -> tuple[torch.Tensor, dict]:
    """The 3D step's loss with the ground-truth camera instead of the predicted one."""
    images = batch["image"]
    feats = model.encode(images, model.branches())
    p = model.predict_3d(feats, False)
    verts = p.verts
    rec, alpha = model.render(verts, p.texture, batch["R"], batch["T"], p.background)
    shape_step = objectives_of(model).steps["3d"]
    loss = sum(v.mean() for v in shape_step.reconstruction(rec, images).values())
    if model.shape.mask.active_dims > 0:
        loss = loss + sum(shape_step.regularizer(verts).values())
    return loss, {"rec": rec, "alpha": alpha, "shape_code": p.shape_code, "texture_code": p.texture_code}


_OBJECTIVES: dict[int, Objectives] = {}


def objectives_of(model: Unicorn) -> Objectives:
    """The training objectives of ``model`` (built once per model)."""
    if id(model) not in _OBJECTIVES:
        _OBJECTIVES[id(model)] = Objectives.from_config(model.config["loss"], model)
    return _OBJECTIVES[id(model)]


def run(control: Control, model_cfg: dict, root: str, args: argparse.Namespace) -> dict[str, float]:
    from unicorn.data import build_dataset

    torch.manual_seed(args.seed)
    train = build_dataset("synthetic", "train", root, 32, "car")
    test = build_dataset("synthetic", "test", root, 32, "car", views="all")
    # Python ints: the dataset warns for every item indexed by a tensor
    chosen = torch.randperm(len(test), generator=torch.Generator().manual_seed(0))[:64].tolist()
    views = torch.utils.data.Subset(test, chosen)
    held = next(iter(torch.utils.data.DataLoader(views, batch_size=64)))
    model = Unicorn(model_cfg)
    model.set_active_dims(shape=control.shape_dims, texture=control.texture_dims)
    model.set_stage_switches(translation=False, deformation=control.shape_dims > 0, scale=True)
    opt_3d = torch.optim.Adam(model.parameters(), lr=args.lr)
    opt_pose = torch.optim.Adam(model.parameters(), lr=args.lr) if control.adam_per_step else opt_3d
    loader = torch.utils.data.DataLoader(
        train, batch_size=16, shuffle=True, drop_last=True, generator=torch.Generator().manual_seed(args.seed)
    )
    it, start = 0, time.perf_counter()
    while it < args.iterations:
        for batch in loader:
            pose = control.pose_steps and it % 2 == 0
            opt = opt_pose if pose else opt_3d
            opt.zero_grad(set_to_none=True)
            loss = (
                objectives_of(model).pose_step(model, batch["image"])["total"]
                if pose
                else gt_pose_step(model, batch)[0]
            )
            loss.backward()
            opt.step()
            it += 1
            if it >= args.iterations:
                break
    model.eval()
    hidden: list[torch.Tensor] = []
    hook = model.shape.regressor[-2].register_forward_hook(lambda m, i, o: hidden.append(o.detach()))
    with torch.no_grad():
        _, out = gt_pose_step(model, held)
    hook.remove()
    err, base = color_errors(
        mean_foreground_color(out["rec"], out["alpha"], interior=1),
        mean_foreground_color(held["image"], held["mask"], interior=1),
    )
    pred, gt = out["alpha"][:, 0] > 0.5, held["mask"][:, 0] > 0.5
    iou = ((pred & gt).sum((1, 2)).float() / (pred | gt).sum((1, 2)).clamp_min(1)).mean()
    return {
        "colour ratio": float(err.nanmean() / base.nanmean()),
        "mask IoU": float(iou),
        "texture code std": float(code_spread(out["texture_code"], control.texture_dims).mean()),
        "shape code std": float(code_spread(out["shape_code"], control.shape_dims).mean())
        if control.shape_dims
        else float("nan"),
        "shape units alive": float(active_units(hidden[0]).sum()),
        "minutes": (time.perf_counter() - start) / 60,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iterations", type=positive_int, default=800, help="training iterations of each row")
    p.add_argument("--lr", type=positive_float, default=2e-4, help="Adam learning rate")
    p.add_argument("--seed", type=seed_number, default=0)
    p.add_argument(
        "--controls",
        type=row_numbers(len(CONTROLS)),
        default="all",
        help=f"comma-separated row numbers (0 to {len(CONTROLS) - 1}) or 'all'",
    )
    p.add_argument("--cache", help="synthetic dataset cache folder (default: the config's)")
    args = p.parse_args()
    chosen = CONTROLS if args.controls == "all" else [CONTROLS[i] for i in args.controls]
    model_cfg, root = compose_model_config(args.cache)
    rows = {}
    for control in chosen:
        rows[control.name] = run(control, model_cfg, root, args)
        print(control.name, {k: round(v, 3) for k, v in rows[control.name].items()}, flush=True)
    cols = list(next(iter(rows.values())))
    print(f"\n{args.iterations} iterations, Adam lr {args.lr}, seed {args.seed}, batch 16, 64 held-out views\n")
    print("| control | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for name, row in rows.items():
        print(f"| {name} | " + " | ".join(f"{row[c]:.3f}" for c in cols) + " |")


if __name__ == "__main__":
    main()
