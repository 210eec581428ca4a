"""Where a trained model's pose error comes from: its candidates, the choice among them, or the loss that trains it?

For every test view of a dataset with ground-truth poses, the model's K pose candidates are compared with the
ground truth in the learned canonical frame aligned on the selected candidates (``align_canonical_frame``, as the
evaluation does), and each candidate's reconstruction is scored with the training's reconstruction loss
(``ReconstructionLoss`` of the model's own ``loss`` settings, over its predicted background). Printed per model:

- ``selected``: the share of views whose most likely candidate is within 30 degrees (the evaluation's
  ``rot-acc-30``), and ``turned round`` (above 150 degrees);
- ``any``: the share with some candidate within 30 degrees (``rot-acc-30-any``): what a perfect choice would give;
- ``loss-best``: the share whose best-reconstructing candidate is within 30 degrees: what the pose step's loss
  can tell apart (the ``assigned`` pose objective trains the probabilities towards that candidate);
- ``head = loss-best``: how often the most likely candidate is the best-reconstructing one;
- ``max prob``: the mean probability of the selected candidate (1 / K: no preference);
- ``azim 30`` / ``half turn``: the share with the azimuth within 30 degrees, and within 30 degrees of it or of
  its half turn; ``elev`` / ``roll``: the median absolute elevation and roll errors (degrees);
- ``own pose by loss`` / ``own pose gap``: whether each reconstruction, turned about its vertical axis, fits its
  image better within 30 degrees of the selected pose than beyond (``experiments/shape_controls.py``'s
  ``loss-pose`` / ``loss-gap`` at the model's own pose): a reconstruction symmetric enough to look alike from
  every side scores low, whatever the pose;
- ``cand. azim std min`` / ``max``: the smallest and largest standard deviation of a candidate's azimuth over the
  views (degrees): near 0 for a candidate that predicts one azimuth for every image;
- ``mask IoU``: the evaluation's mask IoU (``unicorn-eval``'s hard render at the masks' side, ``mask_supersample``
  of the default protocol) of the selected candidate's reconstruction, over every view, over the views whose
  selected candidate is within 30 degrees, and over the others: how much of a model's mask IoU its pose misses
  cost;
- the same shares per ground-truth elevation band when the elevations vary;
- with ``--by-azimuth``, a table per band of ground-truth azimuth: the share within 30 degrees, the share turned
  round, and the views that select each candidate (:func:`by_azimuth`): a candidate selected for two bands half a
  turn apart (side views seen from the left and from the right, say) is a fold.

Wide gaps between ``any`` and ``selected`` with ``loss-best`` close to ``selected`` say that the candidates are
there but the reconstruction loss cannot tell the right one from the others.

    python experiments/pose_candidates.py RUN/checkpoints/last.ckpt [RUN2/checkpoints/last.ckpt ...]
    python experiments/pose_candidates.py --by-azimuth RUN/checkpoints/last.ckpt

The dataset is the one each run was trained on (its synthetic settings), or ``--root``. About a minute per model
on a 2-core CPU for the 480 test views of the default experiment.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from shape_controls import loss_picks_pose, turn_losses  # a sibling script

from unicorn.data import build_dataset, dataset_root
from unicorn.evaluation import EvalOptions
from unicorn.evaluation.rendering import hard_render
from unicorn.io.checkpoints import load_model
from unicorn.metrics import mask_iou
from unicorn.metrics.pose import align_canonical_frame, azimuth_error, geodesic_error, rotation_to_azim_elev_roll
from unicorn.objectives.losses import ReconstructionLoss

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import add_checkpoints_and_root, positive_int  # noqa: E402


@torch.no_grad()
def candidates(model, data, batch_size: int) -> dict[str, torch.Tensor]:
    """Every view's candidate rotations (K, N, 3, 3), azimuths (K, N), probabilities (K, N), reconstruction
    losses (K, N), ground-truth rotation (N, 3, 3) and the losses of its reconstruction at the selected pose turned
    about the vertical axis (N, A; :func:`shape_controls.turn_losses`) and the selected candidate's mask IoU (N,)."""
    loss = ReconstructionLoss.from_config(model.config["loss"])
    supersample = EvalOptions().mask_supersample
    per_view = ("R_gt", "turns", "iou")  # (N, ...); the others are per candidate, (K, N, ...)
    out: dict[str, list[torch.Tensor]] = {k: [] for k in ("R", "azim", "probs", "loss", *per_view)}
    for start in range(0, len(data), batch_size):
        items = [data[i] for i in range(start, min(start + batch_size, len(data)))]
        images = torch.stack([it["image"] for it in items])
        pred = model.predict(images)
        K, B = pred.poses.probs.shape
        R, T = pred.poses.flat()
        bkg = None if pred.background is None else pred.background.repeat(K, 1, 1, 1)
        rec, _ = model.render(pred.verts.repeat(K, 1, 1), pred.texture.repeat(K, 1, 1, 1), R, T, bkg)
        terms = loss(rec, images.repeat(K, 1, 1, 1))
        out["R"].append(pred.poses.R)
        out["azim"].append(pred.poses.angles[..., 0])
        out["probs"].append(pred.poses.probs)
        out["loss"].append(torch.stack(list(terms.values())).sum(0).view(K, B))
        out["R_gt"].append(torch.stack([it["R"] for it in items]))
        out["turns"].append(turn_losses(model, pred, images, pred.R, pred.T, loss))
        masks = torch.stack([it["mask"] for it in items])
        hard = hard_render(model, pred.verts, pred.texture, pred.R, pred.T, masks.shape[-1], supersample)
        out["iou"].append(mask_iou(hard.images[:, 3:], masks, reduction="none"))
    return {k: torch.cat(v, dim=0 if k in per_view else 1) for k, v in out.items()}


def breakdown(c: dict[str, torch.Tensor]) -> dict[str, float]:
    """The shares and errors listed in the module docstring, from :func:`candidates`."""
    K, N = c["probs"].shape
    views = torch.arange(N)
    chosen = c["probs"].argmax(0)
    Q = align_canonical_frame(c["R"][chosen, views], c["R_gt"])
    R = Q @ c["R"]  # (K, N, 3, 3) in the ground truth's frame
    err = geodesic_error(R, c["R_gt"].unsqueeze(0))  # (K, N)
    loss_best = c["loss"].argmin(0)
    selected = err[chosen, views]
    azim, elev, roll = rotation_to_azim_elev_roll(R[chosen, views])
    azim_gt, elev_gt, roll_gt = rotation_to_azim_elev_roll(c["R_gt"])
    azim_err = azimuth_error(azim, azim_gt)
    share = lambda mask: float(mask.float().mean())  # noqa: E731
    result: dict[str, float] = {
        "selected": share(selected < 30),
        "turned round": share(selected > 150),
        "any": share(err.min(0).values < 30),
        "loss-best": share(err[loss_best, views] < 30),
        "head = loss-best": share(chosen == loss_best),
        "max prob": float(c["probs"].max(0).values.mean()),
        "azim 30": share(azim_err < 30),
        "half turn": share((azim_err < 30) | (azim_err > 150)),
        "elev": float((elev - elev_gt).abs().median()),
        "roll": float((roll - roll_gt).abs().median()),
    }
    spread = c["azim"].std(1)  # (K,) degrees: a candidate that no longer turns with the image has ~0
    result["cand. azim std min"], result["cand. azim std max"] = float(spread.min()), float(spread.max())
    right = selected < 30
    result["mask IoU"] = float(c["iou"].mean())
    result["mask IoU, selected within 30"] = float(c["iou"][right].mean()) if right.any() else float("nan")
    result["mask IoU, the others"] = float(c["iou"][~right].mean()) if (~right).any() else float("nan")
    own = loss_picks_pose(c["turns"])
    result["own pose by loss"], result["own pose gap"] = own["loss-pose"], own["loss-gap"]
    if float(elev_gt.max() - elev_gt.min()) > 1.0:
        edges = torch.linspace(float(elev_gt.min()), float(elev_gt.max()) + 1e-3, 5).round().tolist()
        for lo, hi in zip(edges[:-1], edges[1:]):
            band = (elev_gt >= lo) & (elev_gt < hi)
            result[f"selected, elevation {lo:.0f} to {hi:.0f}"] = share(selected[band] < 30)
    return result


def by_azimuth(c: dict[str, torch.Tensor], bins: int = 12) -> list[dict[str, object]]:
    """Per band of ground-truth azimuth (``bins`` equal bands from 0 degrees): the views, the share whose selected
    candidate is within 30 degrees, the share turned round, and how many views select each candidate (after the
    global alignment, as :func:`breakdown`). A candidate selected for two bands half a turn apart is a fold: the
    model sees those views as one."""
    K, N = c["probs"].shape
    chosen = c["probs"].argmax(0)
    views = torch.arange(N)
    Q = align_canonical_frame(c["R"][chosen, views], c["R_gt"])
    selected = geodesic_error(Q @ c["R"][chosen, views], c["R_gt"])
    azim_gt, _, _ = rotation_to_azim_elev_roll(c["R_gt"])
    band = (torch.remainder(azim_gt, 360.0) * bins / 360.0).long().clamp(max=bins - 1)
    rows = []
    for b in range(bins):
        m = band == b
        n = int(m.sum())
        rows.append(
            {
                "azimuth": f"{b * 360 // bins}-{(b + 1) * 360 // bins}",
                "views": n,
                "within 30": float((selected[m] < 30).float().mean()) if n else float("nan"),
                "turned round": float((selected[m] > 150).float().mean()) if n else float("nan"),
                "views per candidate": torch.bincount(chosen[m], minlength=K).tolist(),
            }
        )
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoints_and_root(p)
    p.add_argument(
        "--dataset",
        default="synthetic",
        choices=("synthetic", "shapenet_nmr"),
        help="the registered dataset that reads --root, every test view of it (default: synthetic)",
    )
    p.add_argument("--batch-size", type=positive_int, default=64, help="views per forward pass")
    p.add_argument("--by-azimuth", action="store_true", help="also a table per band of ground-truth azimuth")
    args = p.parse_args()

    results = {}
    for path in args.checkpoints:
        model, info = load_model(path)
        model.eval()
        d = info.dataset or {}  # none in a checkpoint saved without its run's data
        root = args.root or dataset_root("synthetic", d.get("root"), d.get("categories"), d.get("synthetic"))
        size, categories = model.config["image_size"], d.get("categories")
        data = build_dataset(args.dataset, "test", str(root), img_size=size, categories=categories, views="all")
        c = candidates(model, data, args.batch_size)
        results[path] = breakdown(c)
        if args.by_azimuth:
            rows = by_azimuth(c)
            print(f"{path}, per ground-truth azimuth band (degrees):")
            print("| " + " | ".join(rows[0]) + " |")
            print("|---" * len(rows[0]) + "|")
            for row in rows:
                cells = [f"{v:.2f}" if isinstance(v, float) else str(v) for v in row.values()]
                print("| " + " | ".join(cells) + " |")
    keys = list(dict.fromkeys(k for r in results.values() for k in r))
    print("| model | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for path, r in results.items():
        print(f"| {path} | " + " | ".join(f"{r[k]:.3f}" if k in r else "–" for k in keys) + " |")


if __name__ == "__main__":
    main()
