"""Where a trained model's shape error comes from: the category's shape, or the lack of per-image shapes?

Scores, on every test object of a synthetic (or ShapeNet-NMR) dataset, Chamfer-L1 after unit-cube normalisation
and ICP (``unicorn.metrics.evaluate_meshes``, the evaluation's ``chamfer-L1-ICP``) of five meshes on the model's
template topology:

- ``own fit``: the template fitted to that object's own ground-truth points (``fit_mean_shape`` on one cloud): the
  best this mesh can do, the floor of any model using it;
- ``mean shape``: the template fitted to all training objects' ground-truth points: the best single shape;
- ``model, object frame``: the model's prediction for the object's image, compared in the model's canonical frame
  (no pose: the learned frame of the synthetic cars matches the ground truth's up to the ICP);
- ``model, predicted pose``: the same prediction mapped through the predicted and ground-truth poses (the
  evaluation's protocol);
- ``model's own mean``: the average of the model's predictions over the test objects, in its canonical frame.

and, across the objects, the Pearson correlation between the predicted and the ground-truth height / length and
width / length ratios: whether the per-image shapes follow each object's proportions. A model that outputs one
shape for every image has its own mean as prediction (win share 0.5, correlations undefined).

    python experiments/shape_gap.py RUN/checkpoints/last.ckpt --root $UNICORN_CACHE/synthetic_32px/nmr_car_n100_s0_v2

About a minute on a 2-core CPU for the 20 test cars of the default experiment.
"""

from __future__ import annotations

import argparse

import torch

from unicorn.evaluation.baselines import fit_mean_shape, training_point_clouds
from unicorn.evaluation.evaluator import build_eval_dataset
from unicorn.io.checkpoints import load_model
from unicorn.metrics.mesh_evaluator import evaluate_meshes

ROWS = ["own fit", "mean shape", "model, object frame", "model, predicted pose", "model's own mean"]


def ratios(points: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) object-frame points -> (B, 2) height / length and width / length (x: length, y: up, z: width)."""
    extent = points.amax(1) - points.amin(1)
    return torch.stack([extent[:, 1] / extent[:, 0], extent[:, 2] / extent[:, 0]], 1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--root", required=True, help="the dataset folder (holds metadata.yaml)")
    p.add_argument("--dataset", default="synthetic", choices=("synthetic", "shapenet_nmr"))
    p.add_argument("--categories", default=None)
    p.add_argument("--num-points", type=int, default=5000)
    p.add_argument("--icp-iterations", type=int, default=30)
    p.add_argument("--fit-iterations", type=int, default=150, help="iterations of each template fit")
    p.add_argument("--max-images", type=int, default=None)
    args = p.parse_args()

    model, _ = load_model(args.checkpoint)
    faces, template = model.template.faces, model.template.verts
    data = build_eval_dataset(args.dataset, args.root, "test", model.config["image_size"], args.categories)
    items = [data[i] for i in range(len(data) if args.max_images is None else min(len(data), args.max_images))]
    points = torch.stack([it["points"] for it in items])
    with torch.no_grad():
        pred = model.predict(torch.stack([it["image"] for it in items]))
    mean = fit_mean_shape(template, faces, training_point_clouds(args.root, args.categories), args.fit_iterations)
    own_fits = torch.stack([fit_mean_shape(template, faces, [it["points"]], args.fit_iterations) for it in items])
    B = len(items)
    kw = dict(num_points=args.num_points, icp_iterations=args.icp_iterations)
    pose = dict(R_pred=pred.R, T_pred=pred.T, R_gt=torch.stack([it["R"] for it in items]))
    pose["T_gt"] = torch.stack([it["T"] for it in items])
    meshes = {
        "own fit": (own_fits, {}),
        "mean shape": (mean.expand(B, -1, -1), {}),
        "model, object frame": (pred.verts, {}),
        "model, predicted pose": (pred.verts, pose),
        "model's own mean": (pred.verts.mean(0).expand(B, -1, -1), {}),
    }
    scores = {
        k: evaluate_meshes(v, faces, points, None, **extra, **kw)["chamfer-L1-ICP"] for k, (v, extra) in meshes.items()
    }

    print(f"{B} test objects, {args.num_points} points, {args.icp_iterations} ICP iterations\n")
    print("| mesh scored on each test object | Chamfer-L1 ICP (mean) |")
    print("|---|---|")
    for name in ROWS:
        print(f"| {name} | {float(scores[name].mean()):.3f} |")
    ours, own_mean = scores["model, object frame"], scores["model's own mean"]
    wins = (ours < own_mean).float() + 0.5 * (ours == own_mean).float()  # a tie is half a win, as shape-win-own
    print(f"\nper-image shape closer than the model's own mean on {float(wins.mean()):.2f} of them (ties: half)")
    pr, gr = ratios(pred.verts), ratios(points)
    for j, name in enumerate(("height / length", "width / length")):
        r = torch.corrcoef(torch.stack([pr[:, j], gr[:, j]]))[0, 1]
        print(
            f"{name}: correlation predicted vs ground truth {float(r):.2f} "
            f"(spread: predicted {float(pr[:, j].std()):.3f}, ground truth {float(gr[:, j].std()):.3f})"
        )


if __name__ == "__main__":
    main()
