"""Does unicorn learn? Reconstruction quality on the synthetic benchmark, against baselines and ablations.

Trains the README's default experiment (``experiment=synthetic``: procedural cars, ShapeNet-NMR layout,
32 px, the tiny model), or the one ``--experiment`` names (``synthetic_long``: 200 cars and a wider texture
branch; ``synthetic64``), with the same iteration budget in five variants, each with
``unicorn-train`` as a user would run it, then scores every final checkpoint on the held-out test models:

- ``full``: the experiment as it is;
- ``no-neighbor``: without the neighbour reconstruction loss (``model.loss.neighbor_weight=0``);
- ``no-progressive``: without progressive conditioning (every code at its full size from the first iteration);
- ``wild``: the ``wild`` mode (random viewpoints, distances, shifts and backgrounds, ``experiment=synthetic_wild``);
- ``chairs``: the experiment on procedural chairs (``dataset.categories=chair``; generated on first use into
  ``$UNICORN_CACHE/synthetic_32px`` beside the cars, about a minute).

Seeds: ``--seeds 0,1,2`` trains every variant once per seed (``seed=S``: weights, data order and texture draws;
the dataset is the same) into ``<out>/runs/<variant>/seed<S>`` and scores each; the table then shows, per
variant, ``mean ± std`` over the seeds (sample standard deviation, n-1) and ``results.json`` keeps every seed's
values. Jobs: ``--jobs N`` trains up to N runs at once, each with ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` set to
``max(1, cores // N)`` (never above an ``OMP_NUM_THREADS`` already set for the benchmark itself); the scoring runs
one model after the other once training is over. A finished run (``done.json`` in its folder) is reused unless
``--retrain``; an interrupted one goes on from its last checkpoint (``ckpt_path=last``). Each run's wall minutes
are recorded (runs that share the machine each take longer than one alone).

Baselines, per category (cars for ``full`` / ``no-neighbor`` / ``no-progressive`` / ``wild``, which share the
car models; chairs for ``chairs``), measured on the first run's dataset of that category: the untrained template
(the model's ellipsoid at the anchor pose of the first candidate; rows ``template (anchor pose)`` and
``template, chairs``) and the best single mean shape (one mesh with the template's topology fitted to every
training model's ground-truth point cloud of that category, rendered at the ground-truth pose: the best one can
do without looking at the image, and generous since its pose is perfect; rows ``mean shape (GT pose)`` and
``mean shape (GT pose), chairs``); and the silhouette floor (each test object's template fitted to the masks of
all its views at their ground-truth poses with the model's own renderer and regularisers,
``unicorn.evaluation.fit_silhouettes``: what silhouettes at this image size can say about a shape, with no pose
error and no generalisation gap; rows ``silhouette fit (GT poses, every view)`` and ``..., chairs``;
``--silhouette-iterations 0`` leaves it out; 12 minutes for the 20 test cars on one busy thread).

Metrics (see unicorn.evaluation): on one fixed view per test model, ``chamfer-L1-ICP`` (unit-cube normalised,
anisotropic-scale ICP) and ``chamfer-L1`` (prediction mapped into the ground-truth frame through the predicted
and the ground-truth camera: shape and pose together); on every view of every test model, ``mask-iou``, the
rotation errors after aligning the learned canonical frame with one global rotation (the rotation with the
lowest median error among the chordal least-squares solution and the per-image relative rotations, refined on
the inliers: ``unicorn.metrics.align_canonical_frame``) and the share of images choosing each pose candidate.

Instance-level columns (``unicorn.metrics.instance``), which tell reconstructions of each object from the
category mean: ``rot-flip-150`` (share of views predicted turned round, beside ``rot-acc-30``); ``color-err``
(per view, L1 between the mean foreground colours of the reconstruction and of the input, over mask interiors:
each mask eroded by one pixel, so that border pixels mixing object and background do not count) beside
``color-err-mean`` (the same for predicting the test views' average colour for every view) and their ratio
``color-ratio``; ``shape-win``, the share of test objects on which the model's Chamfer-L1 after ICP is below the
mean shape's of its category on the same object (``chamfer-L1-ICP-mean-shape``). That mean shape is fitted to
the 3D ground truth, so losing to it can mean an inaccurate category shape as much as one shape for all; the
model's own average shape over the test objects, placed with each image's predicted pose
(``chamfer-L1-ICP-own-mean``), separates the two: ``shape-win-own``, the share of objects on which the model's
per-image shape is closer than its own average, is 0.5 (ties) for a model with one shape for every image.

Bars, for the ``full`` car model (its mean over the seeds; none for chairs): ``chamfer-L1-ICP`` at most 0.8 x the
mean shape's (below the mean-shape baseline), ``color-ratio`` at most 0.3, ``rot-acc-30`` at least 0.95,
``rot-flip-150`` at most 0.03, ``mask-iou`` at least 0.90 and ``cand-share-min`` at least 0.05 (no pose
collapse). Each is printed met / MISSED; the exit status is 1 if one is missed. After the table, a line says
whether the paper's ablation order holds on the means (full below no-neighbor and no-progressive on the car
Chamfer-L1 after ICP), and the same comparison on the instance metrics colour ratio and flip rate.

Writes ``results.md`` / ``results.json`` (the table, the per-seed values, the bars, the order, the machine, the
times), ``curves.png`` (held-out metrics against iterations, from each run's ``heldout.csv``) and
``pictures/report.png`` (input, reconstruction, mask, the mesh from three viewpoints, for ten held-out images of
the ``full`` model's first seed) into ``--out``; training logs in ``<out>/logs``.

Time: a run of ``experiment=synthetic`` (4800 iterations) takes about 10-11 minutes on a quiet 2-core CPU with
2 threads, 12-16 minutes with one thread (``synthetic_long``: about 26 minutes with 2 threads); scoring about
2 minutes per run, plus about 3 minutes of baselines per category. All five variants with one seed: about an
hour and a half with ``--jobs 2``; with ``--seeds 0,1,2``, about four hours.

The categories table (``--table categories``): one recipe (``--experiment``, default ``synthetic_9600``: the
default's schedule twice as long) trained on each synthetic
category in the NMR views, car, chair, table, lamp and mug, and on cars and chairs in the ``wild`` mode (the wild
rows alone: ``--categories car-wild,chair-wild``); only the category
and the mode change (``dataset.categories=X dataset.synthetic.mode=Y``, and for the wild mode what
``experiment=synthetic_wild`` adds: the ``real`` family's real-image settings, ``family=real``, and the scale held
through stage 1, ``schedule.curriculum.scale=${schedule.milestones[0]}``; ``--data-root`` sets ``dataset.root``
for every run). Each run trains about 23 minutes alone on a quiet 2-core CPU, 31-34 minutes with one thread
beside another; the eight runs with ``--jobs 2`` about two hours and a quarter, then the scoring. Cars over
``--car-seeds`` (default 0,1,2; the car entries, in both modes), the others over ``--seeds`` (default 0);
``--categories`` picks entries. Each
category's datasets are generated before training starts (once, not by concurrent runs). Rows per entry: the
silhouette fit with ground-truth poses (what these views allow), then the model (mean ± std over its seeds).
Columns: the shape retrieval among the test objects (``shape-top3``, the right object among the 3 closest
normalised shapes in the image's view, and its floor ``shape-top3-floor``, the model's mean canonical shape times
each image's scale; chance 3 / test objects), Chamfer-L1 after ICP, colour ratio, the colour ratio over the pixels
both silhouettes cover (``color-ratio-overlap``: the texture's colour without what a wrong silhouette paints),
rotation accuracy at 30 degrees, flipped views and mask IoU. ``--dry-run`` prints the training commands and stops.

    python benchmarks/quality.py                                  # five variants, seed 0
    python benchmarks/quality.py --runs full,no-neighbor,no-progressive --seeds 0,1,2 --jobs 2
    python benchmarks/quality.py --runs full --steps 600 --out /tmp/q   # a quick look
    python benchmarks/quality.py --experiment synthetic_long --runs full --seeds 0,1,2 --silhouette-iterations 0
    python benchmarks/quality.py --table categories --jobs 2 --out /tmp/categories   # seven entries, cars x 3 seeds
    python benchmarks/quality.py --table categories --categories car-wild,chair-wild --jobs 2   # the wild rows
    python benchmarks/quality.py --table categories --categories chair,mug --dry-run
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import torch

#: the variants: (experiment, overrides); None is the benchmark's ``--experiment`` (default ``synthetic``)
RUNS: dict[str, tuple[str | None, list[str]]] = {
    "full": (None, []),
    "no-neighbor": (None, ["model.loss.neighbor_weight=0"]),
    "no-progressive": (None, ["model.stages.shape=[16,16,16,16]", "model.stages.texture=[16,16,16,16]"]),
    "wild": ("synthetic_wild", []),
    "chairs": (None, ["dataset.categories=chair"]),
}


#: the categories table's entries: name -> (synthetic category, synthetic mode)
CATEGORY_RUNS: dict[str, tuple[str, str]] = {
    "car": ("car", "nmr"),
    "chair": ("chair", "nmr"),
    "table": ("table", "nmr"),
    "lamp": ("lamp", "nmr"),
    "mug": ("mug", "nmr"),
    "car-wild": ("car", "wild"),
    "chair-wild": ("chair", "wild"),
}
#: the entries trained over ``--car-seeds`` (the others over ``--seeds``)
CAR_ENTRIES = ("car", "car-wild")
#: per synthetic mode, what the recipe takes from elsewhere: the wild mode's real-image settings (background
#: model, viewpoint ranges, texture averaging) are the ``real`` family's, and its anisotropic scale waits for
#: stage 2 (the paper's real-image curriculum: the recipe's first milestone); with ``--experiment synthetic``
#: the wild entry is ``experiment=synthetic_wild`` (tests/benchmarks/test_quality.py compares the two)
MODE_OVERRIDES: dict[str, list[str]] = {
    "nmr": [],
    "wild": ["family=real", "schedule.curriculum.scale=${schedule.milestones[0]}"],
}
#: each table's recipe when ``--experiment`` names none
DEFAULT_EXPERIMENT = {"ablations": "synthetic", "categories": "synthetic_9600"}
TABLES = ("ablations", "categories")
#: the categories table's bars, per entry (mean over its seeds), as (metric, comparison, limit, reference):
#: reference None: the limit itself; "silhouette": limit x the entry's silhouette-fit value; a metric: limit x
#: the entry's value of that metric
CATEGORY_BARS: dict[str, list[tuple[str, str, float, str | None]]] = {
    "car": [
        ("shape-top3", ">=", 0.6, None),
        ("shape-top3", ">=", 2.0, "shape-top3-floor"),
        ("chamfer-L1-ICP", "<=", 1.1, "silhouette"),
        ("color-ratio", "<=", 0.35, None),
        ("rot-acc-30", ">=", 0.95, None),
        ("rot-flip-150", "<=", 0.03, None),
        ("mask-iou", ">=", 0.90, None),
    ],
    "car-wild": [
        ("rot-acc-30", ">=", 0.80, None),
        ("rot-flip-150", "<=", 0.05, None),
        ("mask-iou", ">=", 0.85, None),
        ("color-ratio", "<=", 0.6, None),
    ],
    "chair-wild": [("rot-acc-30", ">=", 0.70, None), ("mask-iou", ">=", 0.75, None)],
}
#: the bars of the other entries
OTHER_BARS: list[tuple[str, str, float, str | None]] = [
    ("color-ratio", "<=", 0.5, None),
    ("rot-acc-30", ">=", 0.90, None),
    ("mask-iou", ">=", 0.80, None),
    ("shape-top3", ">=", 2.0, "shape-top3-floor"),
]


def experiments() -> list[str]:
    """What ``--experiment`` may name: the shipped ``synthetic*`` experiments that no variant fixes itself."""
    from unicorn.resources import config_dir

    fixed = {experiment for experiment, _ in RUNS.values() if experiment}
    return sorted(p.stem for p in (config_dir() / "experiment").glob("synthetic*.yaml") if p.stem not in fixed)


#: baseline row names of the cars (the bars' reference); other categories get ", <category>s" appended
TEMPLATE_ROW = "template (anchor pose)"
MEAN_SHAPE_ROW = "mean shape (GT pose)"
SILHOUETTE_ROW = "silhouette fit (GT poses, every view)"

#: the bars of the full car model (mean over seeds), as (metric, comparison, limit or baseline multiple)
BARS = [
    ("chamfer-L1-ICP", "<=", 0.8, "x the mean shape's (GT pose)"),
    ("color-ratio", "<=", 0.3, ""),
    ("rot-acc-30", ">=", 0.95, ""),
    ("rot-flip-150", "<=", 0.03, ""),
    ("mask-iou", ">=", 0.90, ""),
    ("cand-share-min", ">=", 0.05, "(no pose collapse)"),
]

#: the paper's ablation order (full better than each ablation, lower is better), checked on the car runs
ORDER_BASE, ORDER_ABLATIONS = "full", ("no-neighbor", "no-progressive")
ORDER_METRICS = [
    ("chamfer-L1-ICP", "Chamfer-L1 ICP"),
    ("color-ratio", "colour ratio"),
    ("rot-flip-150", "flip rate"),
]

COLUMNS = [
    ("chamfer-L1-ICP", "Chamfer-L1 ICP", "{:.3f}"),
    ("chamfer-L1-ICP-mean-shape", "mean shape, same objects", "{:.3f}"),
    ("shape-win", "wins vs mean shape", "{:.2f}"),
    ("chamfer-L1-ICP-own-mean", "own mean shape, same objects", "{:.3f}"),
    ("shape-win-own", "wins vs own mean", "{:.2f}"),
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
#: the categories table's columns
CATEGORY_COLUMNS = [
    ("shape-top3", "shape top-3", "{:.2f}"),
    ("shape-top3-floor", "top-3 floor (scale only)", "{:.2f}"),
    ("chamfer-L1-ICP", "Chamfer-L1 ICP", "{:.3f}"),
    ("color-ratio", "colour ratio", "{:.2f}"),
    ("color-ratio-overlap", "colour ratio, overlap", "{:.2f}"),
    ("rot-acc-30", "rot. acc. 30 deg", "{:.3f}"),
    ("rot-flip-150", "flipped (> 150 deg)", "{:.3f}"),
    ("rot-acc-30-any", "some candidate within 30 deg", "{:.3f}"),
    ("mask-iou", "mask IoU", "{:.3f}"),
    ("train-minutes", "train (min)", "{:.1f}"),
]
FORMATS = {key: fmt for key, _, fmt in COLUMNS + CATEGORY_COLUMNS}
#: the shape-retrieval columns kept from the evaluation of one view per test object
SHAPE_KEYS = tuple(f"shape-{m}{s}" for s in ("", "-gt", "-floor") for m in ("top1", "top3", "mrr")) + (
    "shape-spread-ratio",
    "shape-detail-ratio",
)

Row = dict[str, float]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--out",
        type=Path,
        default=Path("benchmarks/results/quality"),
        help="output folder of the runs and tables (default: benchmarks/results/quality under the current folder)",
    )
    p.add_argument(
        "--table",
        choices=TABLES,
        default="ablations",
        help="ablations: the experiment's variants on cars; categories: one recipe on every synthetic category",
    )
    p.add_argument("--runs", default=",".join(RUNS), help=f"ablations table: comma-separated subset of {list(RUNS)}")
    p.add_argument(
        "--categories",
        default=",".join(CATEGORY_RUNS),
        help=f"categories table: comma-separated subset of {list(CATEGORY_RUNS)}",
    )
    p.add_argument(
        "--seeds",
        default=None,
        help="comma-separated training seeds (default 0); every run is trained once per seed, but the categories "
        "table's car entries, which take --car-seeds",
    )
    p.add_argument(
        "--car-seeds",
        default="0,1,2",
        help=f"categories table: the seeds of the car entries {sorted(CAR_ENTRIES)} (--seeds: the others)",
    )
    p.add_argument("--data-root", help="categories table: dataset.root of every run (default: the experiment's)")
    p.add_argument("--jobs", type=int, default=1, help="train up to this many runs at once")
    p.add_argument(
        "--threads", type=int, help="threads of each training run (default: the cores shared by the --jobs runs)"
    )
    p.add_argument("--dry-run", action="store_true", help="print the training commands and stop")
    p.add_argument(
        "--experiment",
        choices=experiments(),
        help="the recipe of every run but the ablations' wild variant (default: "
        + ", ".join(f"{e} for the {t} table" for t, e in DEFAULT_EXPERIMENT.items())
        + ")",
    )
    p.add_argument("--steps", type=int, help="training iterations (default: the experiment's)")
    p.add_argument("--retrain", action="store_true", help="train again even where a finished run exists")
    p.add_argument("--icp-points", type=int, default=20_000, help="points per mesh in the ICP pass")
    p.add_argument("--icp-iterations", type=int, default=30, help="ICP iterations")
    p.add_argument("--mean-shape-iterations", type=int, default=300, help="iterations of the mean-shape fit")
    p.add_argument(
        "--silhouette-iterations", type=int, default=300, help="iterations of each silhouette fit (0: no such row)"
    )
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("overrides", nargs="*", help="extra unicorn-train overrides for every run (key=value)")
    args = p.parse_args(argv)
    args.experiment = args.experiment or DEFAULT_EXPERIMENT[args.table]
    args.runs = [r for r in args.runs.split(",") if r]
    unknown = set(args.runs) - set(RUNS)
    if unknown or not args.runs:
        p.error(f"unknown runs {sorted(unknown)}; choose from {list(RUNS)}")
    args.categories = [c for c in args.categories.split(",") if c]
    unknown = set(args.categories) - set(CATEGORY_RUNS)
    if unknown or not args.categories:
        p.error(f"unknown categories {sorted(unknown)}; choose from {list(CATEGORY_RUNS)}")
    if args.seeds is not None and args.table == "categories" and set(args.categories) <= set(CAR_ENTRIES):
        cars = sorted(CAR_ENTRIES)
        p.error(f"--seeds applies to none of the chosen entries: the car entries {cars} take --car-seeds")
    args.seeds = "0" if args.seeds is None else args.seeds
    for name in ("seeds", "car_seeds"):
        flag = "--" + name.replace("_", "-")
        try:
            seeds = [int(s) for s in getattr(args, name).split(",") if s.strip()]
        except ValueError:
            p.error(f"{flag} must be comma-separated integers, got {getattr(args, name)!r}")
        if not seeds or len(set(seeds)) != len(seeds):
            p.error(f"{flag} must list distinct integers, got {seeds}")
        setattr(args, name, seeds)
    if args.jobs < 1:
        p.error(f"--jobs must be at least 1, got {args.jobs}")
    if args.threads is not None and args.threads < 1:
        p.error(f"--threads must be at least 1, got {args.threads}")
    if args.steps is not None and args.steps < 1:
        p.error(f"--steps must be at least 1, got {args.steps}")
    for name in ("icp_points", "icp_iterations", "mean_shape_iterations", "silhouette_iterations"):
        if getattr(args, name) < (1 if name == "icp_points" else 0):
            p.error(f"--{name.replace('_', '-')} must be at least {1 if name == 'icp_points' else 0}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        p.error(f"--device {args.device} but CUDA is not available on this machine")
    return args


def plan(args: argparse.Namespace) -> list[Run]:
    """The training runs of the chosen table: every variant (or category entry) once per seed."""
    if args.table == "categories":
        return [
            Run(name, seed, args.out)
            for name in args.categories
            for seed in (args.car_seeds if name in CAR_ENTRIES else args.seeds)
        ]
    return [Run(name, seed, args.out) for name in args.runs for seed in args.seeds]


# ---------------------------------------------------------------------------------------------- training
@dataclass(frozen=True)
class Run:
    """One training run: a variant and a seed, in ``<out>/runs/<name>/seed<seed>``."""

    name: str
    seed: int
    out: Path

    @property
    def dir(self) -> Path:
        return (self.out / "runs" / self.name / f"seed{self.seed}").resolve()

    @property
    def label(self) -> str:
        return f"{self.name}/seed{self.seed}"

    @property
    def log(self) -> Path:
        return self.out / "logs" / f"train_{self.name}_seed{self.seed}.log"


def threads_per_run(jobs: int, threads: int | None = None) -> int:
    """Threads of each training process: ``threads`` if given, else the cores shared by the concurrent runs
    within the caller's limit."""
    if threads is not None:
        return threads
    threads = max(1, (os.cpu_count() or 1) // jobs)
    limit = os.environ.get("OMP_NUM_THREADS", "")
    return min(threads, int(limit)) if limit.isdigit() and int(limit) > 0 else threads


def recipe(name: str, args: argparse.Namespace) -> list[str]:
    """The experiment and overrides that make a run of the chosen table (before its seed, folder and steps).

    Categories table: ``--experiment`` with only the category and the mode changed (plus what the mode takes from
    elsewhere, :data:`MODE_OVERRIDES`, and ``--data-root``); ablations table: the variant's (:data:`RUNS`).
    """
    if args.table == "categories":
        category, mode = CATEGORY_RUNS[name]
        overrides = [f"experiment={args.experiment}", f"dataset.categories={category}"]
        overrides += [f"dataset.synthetic.mode={mode}", *MODE_OVERRIDES[mode]]
        return overrides + ([f"dataset.root={args.data_root}"] if args.data_root else [])
    experiment, extra = RUNS[name]
    return [f"experiment={experiment or args.experiment}", *extra]


def train_command(run: Run, args: argparse.Namespace) -> list[str]:
    overrides = recipe(run.name, args)
    overrides += [f"seed={run.seed}", f"hydra.run.dir={run.dir}", "evaluate.enabled=false"]
    overrides += args.overrides
    if args.steps is not None:
        overrides.append(f"trainer.max_steps={args.steps}")
    if args.retrain or not (run.dir / "checkpoints" / "last.ckpt").exists():
        overrides.append("ckpt_path=null")
    else:
        overrides.append("ckpt_path=last")  # an interrupted benchmark goes on where it stopped
    return [sys.executable, "-m", "unicorn.cli.train", *overrides]


def prepare_data(runs: list[Run], args: argparse.Namespace) -> None:
    """Generate each run's synthetic dataset once, before any training starts (concurrent runs of one category
    would each generate it). The settings are the run's own, composed from its overrides as unicorn-train does."""
    from hydra import compose, initialize_config_dir

    from unicorn.config import validate
    from unicorn.data import prepare_dataset
    from unicorn.resources import config_dir

    done = set()
    for run in runs:
        overrides = [o for o in train_command(run, args)[3:] if not o.startswith(("hydra.", "ckpt_path="))]
        overrides.append(f"paths.output_dir={run.dir}")  # what hydra sets when it runs unicorn-train
        with initialize_config_dir(str(config_dir()), version_base=None):
            d = validate(compose("train", overrides=overrides)).dataset
        if d.name != "synthetic":
            continue
        categories = d.categories if d.categories is None or isinstance(d.categories, str) else list(d.categories)
        key = (str(d.root), str(categories), str(dict(d.synthetic)))
        if key not in done:
            done.add(key)
            print(f"[{run.label}] dataset: {prepare_dataset('synthetic', d.root, categories, dict(d.synthetic))}")


def train_all(runs: list[Run], args: argparse.Namespace) -> dict[Run, float]:
    """Train every run with unicorn-train, up to ``args.jobs`` at once (or reuse finished ones); minutes per run."""
    minutes: dict[Run, float] = {}
    pending = []
    for run in runs:
        done = run.dir / "done.json"
        if done.exists() and not args.retrain:
            minutes[run] = json.loads(done.read_text())["minutes"]
            print(f"[{run.label}] reusing the finished run in {run.dir} ({minutes[run]:.1f} min)", flush=True)
        else:
            pending.append(run)
    threads = threads_per_run(args.jobs, args.threads)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    active: dict[Run, tuple[subprocess.Popen, float, IO[str], list[str]]] = {}
    failed: list[str] = []
    try:
        while pending or active:
            while pending and len(active) < args.jobs and not failed:  # after a failure, start nothing more
                run = pending.pop(0)
                command = train_command(run, args)
                run.dir.mkdir(parents=True, exist_ok=True)
                run.log.parent.mkdir(parents=True, exist_ok=True)
                print(f"[{run.label}] ({threads} threads) {' '.join(command[2:])}", flush=True)
                log_file = open(run.log, "w", encoding="utf-8")  # closed when the process ends
                process = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT, env=env)
                active[run] = (process, time.perf_counter(), log_file, command)
            if not active:
                break
            time.sleep(1.0)
            for run, (process, start, log_file, command) in list(active.items()):
                status = process.poll()
                if status is None:
                    continue
                log_file.close()
                del active[run]
                elapsed = (time.perf_counter() - start) / 60
                if status != 0:
                    failed.append(f"[{run.label}] unicorn-train failed (status {status}); see {run.log}")
                    print(failed[-1], flush=True)
                    continue
                minutes[run] = elapsed
                (run.dir / "done.json").write_text(json.dumps({"minutes": elapsed, "command": command}))
                print(f"[{run.label}] trained in {elapsed:.1f} min", flush=True)
    finally:  # interrupted (or failed): stop the runs this benchmark started; they resume from their checkpoints
        for process, *_ in active.values():
            process.terminate()
        for process, _, log_file, _ in active.values():
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            log_file.close()
    if failed:
        raise SystemExit("\n".join(failed))
    return minutes


# ---------------------------------------------------------------------------------------------- scoring
def load_run(run_dir: Path, device: str) -> tuple[Any, Path, str]:
    """The run's final model, the root of its synthetic dataset and its category (the baselines' key)."""
    from unicorn.data import dataset_root
    from unicorn.data.registry import SYNTHETIC_DEFAULTS
    from unicorn.io import load_model

    model, info = load_model(run_dir / "checkpoints" / "last.ckpt", map_location=device)
    d = info.dataset
    category = d.get("categories") if d.get("categories") is not None else SYNTHETIC_DEFAULTS["category"]
    category = category if isinstance(category, str) else "+".join(sorted(map(str, category)))
    return model, dataset_root("synthetic", d.get("root"), d.get("categories"), d.get("synthetic")), category


def baseline_names(category: str) -> tuple[str, str, str]:
    """(template, mean-shape, silhouette-fit rows) of a category: the cars' plain names, ``..., chairs`` else."""
    if category == "car":
        return TEMPLATE_ROW, MEAN_SHAPE_ROW, SILHOUETTE_ROW
    return f"template, {category}s", f"{MEAN_SHAPE_ROW}, {category}s", f"{SILHOUETTE_ROW}, {category}s"


@functools.cache  # the baselines and the runs share the test set
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
    own_mean: bool = False,
) -> tuple[Row, Any]:
    """The benchmark's metrics of one model (see the module docstring) and the ICP pass's result.

    With ``mean_shape`` ((V, 3) on the model's template), the ICP pass also scores it on every test object and
    reports the share of objects the model wins (``shape-win``); with ``own_mean``, the model's own average shape
    too (``shape-win-own``).
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
            own_mean_shape=own_mean,
            **common,
        ),
        "synthetic",
        device=args.device,
        shape_baseline=mean_shape,
    )
    views = evaluate(
        model,
        every,
        # the shape retrieval is scored on one view per object (its cost grows with the square of the images)
        EvalOptions(num_points=2000, icp_iterations=0, report_samples=0, shape_points=0, **common),
        "synthetic",
        args.device,
    )
    out = {
        k: icp.mean[k]
        for k in (
            "chamfer-L1-ICP",
            "chamfer-L1",
            "chamfer-L1-ICP-mean-shape",
            "shape-win",
            "chamfer-L1-ICP-own-mean",
            "shape-win-own",
            *SHAPE_KEYS,
        )
        if k in icp.mean
    }
    prefixes = ("mask", "rot", "cand", "color")
    out.update({k: views.mean[k] for k in views.columns if k not in out and k.startswith(prefixes)})
    out["n-icp"], out["n-views"] = icp.mean["n-images"], views.mean["n-images"]
    return out, icp


def baselines(model: Any, root: Path, category: str, args: argparse.Namespace) -> tuple[dict[str, Row], torch.Tensor]:
    """A category's baseline rows and its mean shape ((V, 3), which its runs are compared with object by object)."""
    from unicorn.evaluation import mean_shape_baseline, template_baseline, training_point_clouds

    template_row, mean_row, silhouette_row = baseline_names(category)
    rows = {}
    start = time.perf_counter()
    rows[template_row], _ = score(template_baseline(model), root, args)
    clouds = training_point_clouds(root)
    mean_model = mean_shape_baseline(model, clouds, iterations=args.mean_shape_iterations)
    rows[mean_row], _ = score(mean_model, root, args, oracle_pose=True)
    if args.silhouette_iterations:
        rows[silhouette_row] = silhouette_fit(model, root, args)
    print(f"[baselines, {category}] scored in {(time.perf_counter() - start) / 60:.1f} min", flush=True)
    return rows, mean_model.fixed_verts.detach()


def silhouette_fit(model: Any, root: Path, args: argparse.Namespace) -> Row:
    """The silhouette floor: every test object's template fitted to the masks of all its views at their
    ground-truth poses (:func:`unicorn.evaluation.fit_silhouettes`), scored like the models (Chamfer-L1 after ICP
    against the object's points; mask IoU over every view; the shape retrieval among the test objects, each
    fitted mesh in the ground-truth object frame, ``shape-top3``)."""
    from unicorn.evaluation import fit_silhouettes
    from unicorn.metrics import evaluate_meshes, sample_points_from_meshes, shape_retrieval

    _, every = test_sets(root, model.config["image_size"])
    views: dict[int, list[int]] = {}
    for i in range(len(every)):
        views.setdefault(every.model_view(i)[0], []).append(i)
    chamfer, iou, fitted, truth = [], [], [], []
    n = 2000
    for indices in views.values():
        items = [every[i] for i in indices]
        masks, R, T = (torch.stack([it[k] for it in items]).to(args.device) for k in ("mask", "R", "T"))
        verts, ious = fit_silhouettes(model, masks, R, T, iterations=args.silhouette_iterations)
        points = items[0]["points"][None].to(args.device)
        kw = dict(num_points=args.icp_points, icp_iterations=args.icp_iterations)
        chamfer.append(float(evaluate_meshes(verts[None], model.template.faces, points, None, **kw)["chamfer-L1-ICP"]))
        iou += ious.tolist()
        fitted.append(sample_points_from_meshes(verts.detach().cpu(), model.template.faces.cpu(), n, seed=0)[0])
        keep = torch.randperm(len(points[0]), generator=torch.Generator().manual_seed(0))[:n]
        truth.append(points[0, keep].cpu())
    row = {"chamfer-L1-ICP": statistics.fmean(chamfer), "mask-iou": statistics.fmean(iou)}
    if len(fitted) > 1:  # the fits are in the ground-truth object frame: the identity is their view
        queries, candidates = torch.stack(fitted).double(), torch.stack(truth).double()
        eye = torch.eye(3, dtype=torch.float64).expand(len(fitted), 3, 3)
        row["shape-top3"] = float(shape_retrieval(queries, eye, candidates, torch.arange(len(fitted)))["top3"].mean())
    return row


def aggregate(per_seed: dict[int, Row]) -> tuple[Row, Row]:
    """(mean, sample standard deviation) of every metric over the seeds; NaN values are left out of both."""
    keys = list(dict.fromkeys(k for row in per_seed.values() for k in row))
    mean, std = {}, {}
    for key in keys:
        values = [row[key] for row in per_seed.values() if key in row and not math.isnan(row[key])]
        mean[key] = statistics.fmean(values) if values else float("nan")
        std[key] = statistics.stdev(values) if len(values) > 1 else float("nan")
    return mean, std


# ---------------------------------------------------------------------------------------------- outputs
def plot_curves(run_dirs: dict[str, dict[int, Path]], path: Path) -> Path | None:
    """Held-out metrics against iterations, one line per run (from each run's heldout.csv): a colour per variant,
    a line style per seed."""
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
        ("shape-win-own", "share of objects beating its own mean shape"),
    ]
    styles = ["-", "--", ":", "-."]
    n_cols = 4
    n_rows = -(-len(panels) // n_cols)
    fig, grid = plt.subplots(n_rows, n_cols, figsize=(4.2 * n_cols, 3.4 * n_rows), squeeze=False)
    axes = list(grid.flat)
    for ax in axes[len(panels) :]:
        ax.axis("off")
    drawn = False
    for i, (name, seeds) in enumerate(run_dirs.items()):
        for j, (seed, run_dir) in enumerate(seeds.items()):
            csv_path = run_dir / "heldout.csv"
            if not csv_path.exists():
                continue
            rows = list(csv.DictReader(csv_path.open()))
            steps = [float(r["step"]) for r in rows]
            label = name if len(seeds) == 1 else f"{name}, seed {seed}"
            for ax, (key, title) in zip(axes, panels):
                values = [float(r[key]) if r.get(key) not in (None, "") else float("nan") for r in rows]
                ax.plot(steps, values, f"C{i % 10}", ls=styles[j % len(styles)], marker="o", markersize=3, label=label)
                ax.set_title(title, fontsize=10)
                ax.set_xlabel("iteration")
                drawn = True
    if not drawn:
        plt.close(fig)
        return None
    axes[0].legend(fontsize=7)
    fig.suptitle("held-out (validation models) metrics during training", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def check_bars(rows: dict[str, Row]) -> list[tuple[str, float, float, bool]]:
    """(bar, value, limit, met) for the full car model (its mean over the seeds); none without both rows."""
    if "full" not in rows or MEAN_SHAPE_ROW not in rows:
        return []
    full, out = rows["full"], []
    for key, op, limit, note in BARS:
        if key == "chamfer-L1-ICP":
            bar, limit = f"{key} {op} {limit} x mean shape (GT pose)", limit * rows[MEAN_SHAPE_ROW][key]
        else:
            bar = f"{key} {op} {limit}" + (f" {note}" if note else "")
        value = full.get(key, float("nan"))
        met = value <= limit if op == "<=" else value >= limit  # NaN: missed
        out.append((bar, value, limit, met))
    return out


def cell(key: str, mean: float, std: float | None = None) -> str:
    """A table value, ``mean ± std`` where there is a standard deviation, ``–`` where there is no value."""
    fmt = FORMATS.get(key, "{:.3g}")
    if mean != mean:
        return "–"
    return fmt.format(mean) + (f" ± {fmt.format(std)}" if std is not None and std == std else "")


def ablation_order(rows: dict[str, Row], stds: dict[str, Row]) -> tuple[str, list[dict[str, Any]]] | None:
    """The paper's order (full below each ablation; lower is better) on the means: a line and the comparisons."""
    others = [name for name in ORDER_ABLATIONS if name in rows]
    if ORDER_BASE not in rows or not others:
        return None
    names = [ORDER_BASE, *others]
    parts, checks = [], []
    for key, label in ORDER_METRICS:
        values = {n: rows[n].get(key, float("nan")) for n in names}
        holds = all(values[ORDER_BASE] < values[n] for n in others)
        detail = ", ".join(f"{n} {cell(key, values[n], stds.get(n, {}).get(key))}" for n in names)
        parts.append((label, f"{'holds' if holds else 'does not hold'} ({detail})"))
        checks.append({"metric": key, "holds": holds, "means": values})
    order = ", ".join(f"{ORDER_BASE} < {n}" for n in others)
    line = f"paper's order ({order} on {parts[0][0]}): {parts[0][1]}"
    if len(parts) > 1:
        line += "; the same order on the instance metrics: " + "; ".join(f"{lab}: {v}" for lab, v in parts[1:])
    return line, checks


def markdown_table(rows: dict[str, Row], stds: dict[str, Row], columns: list[tuple[str, str, str]] = COLUMNS) -> str:
    head = "| model | " + " | ".join(label for _, label, _ in columns) + " |"
    lines = [head, "|" + "---|" * (len(columns) + 1)]
    for name, row in rows.items():
        std = stds.get(name, {})
        cells = [cell(key, row.get(key, float("nan")), std.get(key)) for key, _, _ in columns]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    device = (
        torch.cuda.get_device_name(0) if torch.cuda.is_available() else f"CPU only, {torch.get_num_threads()} threads"
    )
    return f"{cpu}, {os.cpu_count()} cores; {device}; torch {torch.__version__}, Python {platform.python_version()}"


def ablation_rows(
    runs: list[Run], minutes: dict[Run, float], args: argparse.Namespace
) -> tuple[dict[str, Row], dict[str, Row], dict[str, dict[int, Row]], Any]:
    """The ablations table: each category's baselines, every run scored beside its category's mean shape; the
    rows (mean over the seeds), their standard deviations, every run's row and the pictures' report."""
    from unicorn.config.schema import REPORT_SAMPLES

    baseline_rows: dict[str, Row] = {}
    mean_shapes: dict[str, torch.Tensor] = {}
    per_seed: dict[str, dict[int, Row]] = {name: {} for name in args.runs}
    report = None
    # each category's baselines with its first run's model (every run has the same template), so that every run
    # of that category is compared with the same mean shape object by object
    for run in runs:
        t0 = time.perf_counter()
        model, root, category = load_run(run.dir, args.device)
        if category not in mean_shapes:
            rows_c, mean_shapes[category] = baselines(model, root, category, args)
            baseline_rows.update(rows_c)
        pictures = run.name == "full" and report is None
        row, result = score(
            model,
            root,
            args,
            report_samples=REPORT_SAMPLES if pictures else 0,
            mean_shape=mean_shapes[category],
            own_mean=True,
        )
        row["train-minutes"] = minutes[run]
        per_seed[run.name][run.seed] = row
        if pictures:
            from unicorn.evaluation.report import write_report

            report = write_report(
                model,
                result,
                args.out / "pictures",
                f"synthetic {category}, held-out models (seed {run.seed})",
                {},
                turntable_frames=0,
                device=args.device,
            )
        print(
            f"[{run.label}] scored in {(time.perf_counter() - t0) / 60:.1f} min: "
            + ", ".join(f"{k} {v:.4g}" for k, v in row.items()),
            flush=True,
        )

    rows: dict[str, Row] = dict(baseline_rows)
    stds: dict[str, Row] = {}
    for name, seeds in per_seed.items():
        rows[name], std = aggregate(seeds)
        if len(seeds) > 1:
            stds[name] = std
    return rows, stds, per_seed, report


def print_plan(runs: list[Run], args: argparse.Namespace) -> None:
    """What a run of the benchmark would train (``--dry-run``): one command per run, with its thread count."""
    threads = threads_per_run(args.jobs, args.threads)
    print(f"# {len(runs)} training runs, up to {args.jobs} at once, {threads} thread(s) each; output {args.out}")
    for run in runs:
        command = " ".join(train_command(run, args)[2:])
        print(f"OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads} python -m {command}")


def silhouette_row(name: str) -> str:
    """The categories table's silhouette-fit row of an entry."""
    return f"{SILHOUETTE_ROW}, {name}"


def category_rows(
    runs: list[Run], minutes: dict[Run, float], args: argparse.Namespace
) -> tuple[dict[str, Row], dict[str, Row], dict[str, dict[int, Row]]]:
    """The categories table: per entry, its silhouette fit (with its first run's model) and its runs' mean and
    standard deviation over the seeds; and every run's row."""
    per_seed: dict[str, dict[int, Row]] = {name: {} for name in args.categories}
    silhouettes: dict[str, Row] = {}
    for run in runs:
        t0 = time.perf_counter()
        model, root, _ = load_run(run.dir, args.device)
        if run.name not in silhouettes and args.silhouette_iterations:
            silhouettes[run.name] = silhouette_fit(model, root, args)
        row, _ = score(model, root, args)
        row["train-minutes"] = minutes[run]
        per_seed[run.name][run.seed] = row
        shown = ", ".join(f"{k} {row[k]:.4g}" for k, _, _ in CATEGORY_COLUMNS if k in row)
        print(f"[{run.label}] scored in {(time.perf_counter() - t0) / 60:.1f} min: {shown}", flush=True)
    rows: dict[str, Row] = {}
    stds: dict[str, Row] = {}
    for name in args.categories:
        if name in silhouettes:
            rows[silhouette_row(name)] = silhouettes[name]
        rows[name], std = aggregate(per_seed[name])
        if len(per_seed[name]) > 1:
            stds[name] = std
    return rows, stds, per_seed


def check_category_bars(rows: dict[str, Row]) -> list[tuple[str, float, float, bool]]:
    """(bar, value, limit, met) of every entry of the categories table present in ``rows`` (its mean over the
    seeds); a bar relative to the silhouette fit needs that row."""
    out = []
    for name in CATEGORY_RUNS:
        if name not in rows:
            continue
        row = rows[name]
        for key, op, limit, reference in CATEGORY_BARS.get(name, OTHER_BARS):
            if reference == "silhouette":
                if silhouette_row(name) not in rows:
                    continue
                bar = f"{name}: {key} {op} {limit} x the silhouette fit's"
                limit = limit * rows[silhouette_row(name)].get(key, float("nan"))
            elif reference is not None:
                bar, limit = f"{name}: {key} {op} {limit} x {reference}", limit * row.get(reference, float("nan"))
            else:
                bar = f"{name}: {key} {op} {limit}"
            value = row.get(key, float("nan"))
            out.append((bar, value, limit, value <= limit if op == "<=" else value >= limit))  # NaN: missed
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    runs = plan(args)
    if args.dry_run:
        print_plan(runs, args)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    if args.table == "categories":
        prepare_data(runs, args)
    minutes = train_all(runs, args)

    report = None
    if args.table == "categories":
        rows, stds, per_seed = category_rows(runs, minutes, args)
        bars, order, columns, names = check_category_bars(rows), None, CATEGORY_COLUMNS, args.categories
        seeds_note = (
            f"runs: mean ± std (n-1) over seeds {', '.join(map(str, args.car_seeds))} for "
            f"{', '.join(n for n in names if n in CAR_ENTRIES) or 'no entry'}, seed(s) "
            f"{', '.join(map(str, args.seeds))} for the others"
        )
    else:
        rows, stds, per_seed, report = ablation_rows(runs, minutes, args)
        bars, order, columns, names = check_bars(rows), ablation_order(rows, stds), COLUMNS, args.runs
        seeds_note = (
            f"runs: mean ± std (n-1) over seeds {', '.join(map(str, args.seeds))}"
            if len(args.seeds) > 1
            else f"runs: seed {args.seeds[0]}"
        )

    curves = plot_curves({n: {r.seed: r.dir for r in runs if r.name == n} for n in names}, args.out / "curves.png")
    total = (time.perf_counter() - start) / 60
    command = " ".join(["python", "benchmarks/quality.py", *(argv if argv is not None else sys.argv[1:])])
    bar_lines = [
        f"- {'met' if ok else 'MISSED'}: {bar} (value {value:.3f}, bar {limit:.3f})" for bar, value, limit, ok in bars
    ]
    threads = threads_per_run(args.jobs, args.threads)
    lines = [
        markdown_table(rows, stds, columns),
        "",
        seeds_note,
        *([order[0]] if order else []),
        "",
        *([*bar_lines, ""] if bar_lines else []),
        f"command: `{command}`",
        f"machine: {machine()}",
        f"jobs: {args.jobs}, {threads} threads per training run",
        f"total time: {total:.1f} min (training, wall minutes per run: "
        + ", ".join(f"{r.label} {minutes[r]:.1f}" for r in runs)
        + ")",
    ]
    text = "\n".join(lines)
    (args.out / "results.md").write_text(text + "\n")
    (args.out / "results.json").write_text(
        json.dumps(
            {
                "table": args.table,
                "rows": rows,
                "std": stds,
                "per_seed": per_seed,
                "seeds": args.seeds,
                **({"car_seeds": args.car_seeds} if args.table == "categories" else {}),
                "bars": [{"bar": b, "value": v, "limit": t, "met": ok} for b, v, t, ok in bars],
                "order": order[1] if order else None,
                "command": command,
                "machine": machine(),
                "jobs": args.jobs,
                "threads_per_run": threads,
                "minutes": {"total": total, "train": {r.label: minutes[r] for r in runs}},
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
