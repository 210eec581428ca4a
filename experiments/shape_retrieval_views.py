"""How much does one view per object decide the shape retrieval? ``shape-top3`` on one view and on every view.

``benchmarks/quality.py`` scores the shape retrieval (``shape-top1`` / ``shape-top3`` / ``shape-mrr``, beside their
floor, the model's mean canonical mesh times each image's scale, and their ceiling, the ground truth) on one fixed
view of each test object: with 20 test objects each object moves a share by 0.05, and so does its floor. This probe
scores the same retrieval on that view set and on every view of every test object (480 for the synthetic
benchmark), the spread ratios left out (``EvalOptions(shape_spread=False)``: their cost grows with the square of
the views), and prints both per checkpoint.

    python experiments/shape_retrieval_views.py RUN/checkpoints/last.ckpt [RUN2/checkpoints/last.ckpt ...]

The dataset is the one each run was trained on (its synthetic settings), or ``--root``. About two minutes per model
on one thread of a 2-core CPU.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from unicorn.data import build_dataset, dataset_root
from unicorn.evaluation import EvalOptions, evaluate
from unicorn.io.checkpoints import load_model

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import add_checkpoints_and_root, positive_int  # noqa: E402

METRICS = [f"shape-{m}{s}" for s in ("", "-floor", "-gt") for m in ("top1", "top3", "mrr")]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoints_and_root(p)
    p.add_argument("--points", type=positive_int, default=2000, help="points per shape (quality.py's)")
    args = p.parse_args()

    options = EvalOptions(
        "shapenet", progress=False, num_points=args.points, icp_iterations=0, report_samples=0, shape_spread=False
    )
    print("| model | views | images | " + " | ".join(METRICS) + " |")
    print("|---" * (len(METRICS) + 3) + "|")
    for path in args.checkpoints:
        model, info = load_model(path)
        model.eval()
        d = info.dataset or {}  # none in a checkpoint saved without its run's data
        root = args.root or dataset_root("synthetic", d.get("root"), d.get("categories"), d.get("synthetic"))
        size = model.config["image_size"]
        for views in ("random", "all"):  # quality.py's one fixed view per object, then every view
            data = build_dataset("synthetic", "test", str(root), img_size=size, with_points=True, views=views)
            mean = evaluate(model, data, options, "synthetic").mean
            label = "one per object" if views == "random" else "every"
            cells = " | ".join(f"{mean[k]:.3f}" for k in METRICS)
            print(f"| {path} | {label} | {int(mean['n-images'])} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
