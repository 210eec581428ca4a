"""Does unicorn learn? Reconstruction quality on the synthetic benchmark, against baselines and ablations.

Trains the README's default experiment (``experiment=synthetic``: procedural cars, ShapeNet-NMR layout,
32 px, the tiny model) with the same iteration budget in four variants, each with ``unicorn-train`` as a user
would run it, then scores every final checkpoint on the held-out test models:

- ``full``: the experiment as it is;
- ``no-neighbor``: without the neighbour reconstruction loss (``model.loss.neighbor_weight=0``);
- ``no-progressive``: without progressive conditioning (every code at its full size from the first iteration);
- ``wild``: the ``wild`` mode (random viewpoints, distances, shifts and backgrounds, ``experiment=synthetic_wild``).

Two baselines are measured in the same run: the untrained template (the model's ellipsoid at the anchor pose
of the first candidate) and the best single mean shape (one mesh with the template's topology fitted to every
training model's ground-truth point cloud, rendered at the ground-truth pose: the best one can do without
looking at the image, and generous since its pose is perfect).

Metrics (see unicorn.evaluation): on one fixed view per test model, ``chamfer-L1-ICP`` (unit-cube normalised,
anisotropic-scale ICP) and ``chamfer-L1`` (prediction mapped into the ground-truth frame through the predicted
and the ground-truth camera: shape and pose together); on every view of every test model, ``mask-iou``, the
rotation errors after aligning the learned canonical frame with one global rotation (the rotation with the
lowest median error among the chordal least-squares solution and the per-image relative rotations, refined on
the inliers: ``unicorn.metrics.align_canonical_frame``) and the share of images choosing each pose candidate.

Instance-level columns (``unicorn.metrics.instance``), which tell reconstructions of each object from the
category mean: ``rot-flip-150`` (share of views predicted turned round, beside ``rot-acc-30``); ``color-err``
(per view, L1 between the mean foreground colours of the reconstruction and of the input) beside
``color-err-mean`` (the same for predicting the test views' average colour for every view) and their ratio
``color-ratio``; ``shape-win``, the share of test objects on which the model's Chamfer-L1 after ICP is below the
mean shape's on the same object (``chamfer-L1-ICP-mean-shape``).

Writes ``results.md`` / ``results.json`` (the table, the bars, the machine, the times), ``curves.png`` (held-out
metrics against iterations, from each run's ``heldout.csv``) and ``pictures/report.png`` (input,
reconstruction, mask, the mesh from three viewpoints, for ten held-out images) into ``--out``.

    python benchmarks/quality.py                      # about 50 minutes on a quiet 2-core CPU
    python benchmarks/quality.py --runs full --steps 600 --out /tmp/q   # a quick look
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

RUNS: dict[str, list[str]] = {
    "full": ["experiment=synthetic"],
    "no-neighbor": ["experiment=synthetic", "model.loss.neighbor_weight=0"],
    "no-progressive": [
        "experiment=synthetic",
        "model.stages.shape=[16,16,16,16]",
        "model.stages.texture=[16,16,16,16]",
    ],
    "wild": ["experiment=synthetic_wild"],
}

#: the bars of the full model, as (metric, comparison, value or baseline multiple)
BARS = {
    "chamfer-L1-ICP": "at most 0.6 x the template's",
    "mask-iou": "at least 0.85",
    "rot-err-median": "at most 20 degrees",
    "cand-share-min": "at least 0.05 (no pose collapse)",
}

COLUMNS = [
    ("chamfer-L1-ICP", "Chamfer-L1 ICP", "{:.3f}"),
    ("chamfer-L1-ICP-mean-shape", "mean shape, same objects", "{:.3f}"),
    ("shape-win", "wins vs mean shape", "{:.2f}"),
    ("chamfer-L1", "Chamfer-L1 GT pose", "{:.3f}"),
    ("mask-iou", "mask IoU", "{:.3f}"),
    ("color-err", "colour err.", "{:.3f}"),
    ("color-err-mean", "mean-colour err.", "{:.3f}"),
    ("color-ratio", "colour ratio", "{:.2f}"),
    ("rot-err-median", "rot. err. median (deg)", "{:.1f}"),
    ("rot-acc-30", "rot. acc. 30 deg", "{:.3f}"),
    ("rot-flip-150", "flipped (> 150 deg)", "{:.3f}"),
    ("cand-share-min", "min cand. share", "{:.3f}"),
    ("train-minutes", "train (min)", "{:.1f}"),
]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/quality"), help="output folder")
    p.add_argument("--runs", default=",".join(RUNS), help=f"comma-separated subset of {list(RUNS)}")
    p.add_argument("--steps", type=int, help="training iterations (default: the experiment's)")
    p.add_argument("--retrain", action="store_true", help="train again even where a finished run exists")
    p.add_argument("--icp-points", type=int, default=20_000, help="points per mesh in the ICP pass")
    p.add_argument("--icp-iterations", type=int, default=30, help="ICP iterations")
    p.add_argument("--mean-shape-iterations", type=int, default=300, help="iterations of the mean-shape fit")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("overrides", nargs="*", help="extra unicorn-train overrides for every run (key=value)")
    args = p.parse_args(argv)
    unknown = set(args.runs.split(",")) - set(RUNS)
    if unknown:
        p.error(f"unknown runs {sorted(unknown)}; choose from {list(RUNS)}")
    return args


# ---------------------------------------------------------------------------------------------- training
def train(name: str, args: argparse.Namespace) -> tuple[Path, float]:
    """Train one variant with unicorn-train (or reuse a finished run); returns (run dir, minutes)."""
    run_dir = (args.out / "runs" / name).resolve()
    done = run_dir / "done.json"
    if done.exists() and not args.retrain:
        minutes = json.loads(done.read_text())["minutes"]
        print(f"[{name}] reusing the finished run in {run_dir} ({minutes:.1f} min)", flush=True)
        return run_dir, minutes
    overrides = [*RUNS[name], f"hydra.run.dir={run_dir}", "evaluate.enabled=false", *args.overrides]
    if args.steps is not None:
        overrides.append(f"trainer.max_steps={args.steps}")
    if args.retrain or not (run_dir / "checkpoints" / "last.ckpt").exists():
        overrides.append("ckpt_path=null")
    else:
        overrides.append("ckpt_path=last")  # an interrupted benchmark goes on where it stopped
    command = [sys.executable, "-m", "unicorn.cli.train", *overrides]
    print(f"[{name}] {' '.join(command[2:])}", flush=True)
    start = time.perf_counter()
    with open(args.out / f"train_{name}.log", "w") as log_file:
        status = subprocess.run(command, stdout=log_file, stderr=subprocess.STDOUT).returncode
    minutes = (time.perf_counter() - start) / 60
    if status != 0:
        raise SystemExit(f"[{name}] unicorn-train failed (status {status}); see {args.out / f'train_{name}.log'}")
    done.write_text(json.dumps({"minutes": minutes, "command": command}))
    print(f"[{name}] trained in {minutes:.1f} min", flush=True)
    return run_dir, minutes


# ---------------------------------------------------------------------------------------------- scoring
def load_run(run_dir: Path, device: str) -> tuple[Any, Path]:
    """The run's final model and the root of its synthetic dataset."""
    from unicorn.data.datamodule import UnicornDataModule
    from unicorn.io import load_model

    model, info = load_model(run_dir / "checkpoints" / "last.ckpt", map_location=device)
    d = info.dataset
    root = UnicornDataModule("synthetic", d.get("root"), d.get("categories"), synthetic=d.get("synthetic"))
    return model, root.dataset_root()


@functools.cache  # the baselines and the full model share the test set
def test_sets(root: Path, img_size: int) -> tuple[Any, Any]:
    """(one fixed view per test model, every view of every test model), both with ground-truth points."""
    from unicorn.data import build_dataset

    one = build_dataset("synthetic", "test", root, img_size=img_size, with_points=True, views="random")
    every = build_dataset("synthetic", "test", root, img_size=img_size, with_points=True, views="all")
    return one, every


def score(
    model: Any,
    root: Path,
    args: argparse.Namespace,
    oracle_pose: bool = False,
    report_samples: int = 0,
    mean_shape: torch.Tensor | None = None,
) -> tuple[dict[str, float], Any]:
    """The benchmark's metrics of one model (see the module docstring) and the ICP pass's result.

    With ``mean_shape`` ((V, 3) on the model's template), the ICP pass also scores it on every test object and
    reports the share of objects the model wins (``shape-win``).
    """
    from unicorn.evaluation import EvalOptions, evaluate

    one, every = test_sets(root, model.config["image_size"])
    common = dict(protocol="shapenet", progress=False, oracle_pose=oracle_pose, batch_size=64)
    icp = evaluate(
        model,
        one,
        EvalOptions(
            num_points=args.icp_points,
            icp_iterations=args.icp_iterations,
            report_samples=report_samples,
            **common,
        ),
        "synthetic",
        device=args.device,
        shape_baseline=mean_shape,
    )
    views = evaluate(
        model,
        every,
        EvalOptions(num_points=2000, icp_iterations=0, report_samples=0, **common),
        "synthetic",
        args.device,
    )
    out = {
        k: icp.mean[k]
        for k in ("chamfer-L1-ICP", "chamfer-L1", "chamfer-L1-ICP-mean-shape", "shape-win")
        if k in icp.mean
    }
    prefixes = ("mask", "rot", "cand", "color")
    out.update({k: views.mean[k] for k in views.columns if k not in out and k.startswith(prefixes)})
    out["n-icp"], out["n-views"] = icp.mean["n-images"], views.mean["n-images"]
    return out, icp


def baselines(model: Any, root: Path, args: argparse.Namespace) -> tuple[dict[str, dict[str, float]], torch.Tensor]:
    """The baselines' rows and the mean shape ((V, 3), which every variant is compared with object by object)."""
    from unicorn.evaluation import mean_shape_baseline, template_baseline, training_point_clouds

    rows = {}
    start = time.perf_counter()
    rows["template (anchor pose)"], _ = score(template_baseline(model), root, args)
    clouds = training_point_clouds(root)
    mean_model = mean_shape_baseline(model, clouds, iterations=args.mean_shape_iterations)
    rows["mean shape (GT pose)"], _ = score(mean_model, root, args, oracle_pose=True)
    print(f"[baselines] scored in {(time.perf_counter() - start) / 60:.1f} min", flush=True)
    return rows, mean_model.fixed_verts.detach()


# ---------------------------------------------------------------------------------------------- outputs
def plot_curves(run_dirs: dict[str, Path], path: Path) -> Path | None:
    """Held-out metrics against iterations, one line per run (from each run's heldout.csv)."""
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("chamfer-L1-ICP", "Chamfer-L1 after ICP"),
        ("chamfer-L1", "Chamfer-L1, GT-pose aligned"),
        ("mask-iou", "mask IoU"),
        ("rot-err-median", "median rotation error (deg)"),
        ("rot-flip-150", "share of views flipped (> 150 deg)"),
        ("color-ratio", "colour error / mean-colour error"),
        ("shape-win", "share of objects beating the mean shape"),
    ]
    n_cols = 4
    n_rows = -(-len(panels) // n_cols)
    fig, grid = plt.subplots(n_rows, n_cols, figsize=(4.2 * n_cols, 3.4 * n_rows), squeeze=False)
    axes = list(grid.flat)
    for ax in axes[len(panels) :]:
        ax.axis("off")
    drawn = False
    for name, run_dir in run_dirs.items():
        csv_path = run_dir / "heldout.csv"
        if not csv_path.exists():
            continue
        rows = list(csv.DictReader(csv_path.open()))
        steps = [float(r["step"]) for r in rows]
        for ax, (key, title) in zip(axes, panels):
            values = [float(r[key]) if r.get(key) not in (None, "") else float("nan") for r in rows]
            ax.plot(steps, values, marker="o", markersize=3, label=name)
            ax.set_title(title, fontsize=10)
            ax.set_xlabel("iteration")
            drawn = True
    if not drawn:
        plt.close(fig)
        return None
    axes[0].legend(fontsize=8)
    fig.suptitle("held-out (validation models) metrics during training", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def check_bars(rows: dict[str, dict[str, float]]) -> list[tuple[str, float, float, bool]]:
    """(bar, value, threshold, met) for the full model."""
    full, template = rows["full"], rows["template (anchor pose)"]
    limit = 0.6 * template["chamfer-L1-ICP"]
    return [
        ("chamfer-L1-ICP <= 0.6 x template", full["chamfer-L1-ICP"], limit, full["chamfer-L1-ICP"] <= limit),
        ("mask-iou >= 0.85", full["mask-iou"], 0.85, full["mask-iou"] >= 0.85),
        ("rot-err-median <= 20", full["rot-err-median"], 20.0, full["rot-err-median"] <= 20.0),
        ("cand-share-min >= 0.05", full["cand-share-min"], 0.05, full["cand-share-min"] >= 0.05),
    ]


def markdown_table(rows: dict[str, dict[str, float]]) -> str:
    head = "| model | " + " | ".join(label for _, label, _ in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for name, row in rows.items():
        cells = [fmt.format(row[key]) if key in row and row[key] == row[key] else "–" for key, _, fmt in COLUMNS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    device = (
        torch.cuda.get_device_name(0) if torch.cuda.is_available() else f"CPU only, {torch.get_num_threads()} threads"
    )
    return f"{cpu}, {os.cpu_count()} cores; {device}; torch {torch.__version__}, Python {platform.python_version()}"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    names = args.runs.split(",")
    run_dirs, minutes = {}, {}
    for name in names:
        run_dirs[name], minutes[name] = train(name, args)

    rows: dict[str, dict[str, float]] = {}
    report = None
    mean_shape = None
    # the baselines first (with the first run's model: every variant has the same template), so that each
    # variant is compared with the same mean shape object by object
    for name in names:
        t0 = time.perf_counter()
        model, root = load_run(run_dirs[name], args.device)
        if mean_shape is None:
            baseline_rows, mean_shape = baselines(model, root, args)
            rows.update(baseline_rows)
        samples = 10 if name == "full" else 0
        rows[name], result = score(model, root, args, report_samples=samples, mean_shape=mean_shape)
        rows[name]["train-minutes"] = minutes[name]
        if name == "full":
            from unicorn.evaluation.report import write_report

            report = write_report(
                model,
                result,
                args.out / "pictures",
                "synthetic car, held-out models",
                {},
                turntable_frames=0,
                device=args.device,
            )
        print(
            f"[{name}] scored in {(time.perf_counter() - t0) / 60:.1f} min: "
            + ", ".join(f"{k} {v:.4g}" for k, v in rows[name].items()),
            flush=True,
        )

    curves = plot_curves(run_dirs, args.out / "curves.png")
    total = (time.perf_counter() - start) / 60
    table = markdown_table(rows)
    bars = check_bars(rows) if "full" in rows and "template (anchor pose)" in rows else []
    command = " ".join(["python", "benchmarks/quality.py", *(argv if argv is not None else sys.argv[1:])])
    lines = [
        table,
        "",
        *(
            f"- {'met' if ok else 'MISSED'}: {bar} (value {value:.3f}, bar {limit:.3f})"
            for bar, value, limit, ok in bars
        ),
        "",
        f"command: `{command}`",
        f"machine: {machine()}",
        f"total time: {total:.1f} min (training: " + ", ".join(f"{n} {m:.1f}" for n, m in minutes.items()) + " min)",
    ]
    text = "\n".join(lines)
    (args.out / "results.md").write_text(text + "\n")
    (args.out / "results.json").write_text(
        json.dumps(
            {
                "rows": rows,
                "bars": [{"bar": b, "value": v, "limit": t, "met": ok} for b, v, t, ok in bars],
                "command": command,
                "machine": machine(),
                "minutes": {"total": total, **minutes},
            },
            indent=2,
        )
    )
    print()
    print(text)
    if curves:
        print(f"curves: {curves}")
    if report:
        print(f"pictures: {report.get('png')}")
    return 0 if all(ok for *_, ok in bars) else 1


if __name__ == "__main__":
    sys.exit(main())
