"""The evaluation's cost per image, split by stage, this tree against an earlier commit in one run.

Scores the first ``--images`` test images (spread over the split) of a trained checkpoint with
:func:`unicorn.evaluation.evaluate`, beside the same two baselines as the README's main job (the training shapes'
mean shape, fitted once, and the model's own mean shape), at each of ``--settings``:

- ``heldout``: the main job's held-out scoring (``conf/experiment/synthetic.yaml``, ``callbacks.heldout``):
  3000 points, 10 ICP iterations;
- ``final``: the main job's final evaluation (``conf/train.yaml``, ``evaluate``): 50k points, 30 ICP iterations;
- ``full``: UNICORN's full ShapeNet protocol (``unicorn-eval``'s default): 100k points, 100 ICP iterations.

Each tree runs in a fresh process (``--ref REV``: the tree of git revision REV, checked out once with
``git worktree`` under the system's temporary folder, see ``revisions.py``), the variants alternating per
setting, and prints, in milliseconds per image (of the process's CPU time, all threads, on the CPU: what other
load on the machine changes least; of wall time on CUDA):

- per scored shape (``model``, ``mean shape``, ``own mean``): ``sampling`` (surface points),
  ``ICP`` (:func:`~unicorn.metrics.gradient_icp`), ``Chamfer`` (the scores before and after the ICP) and
  ``other`` (alignment, normalisation);
- ``gt search index`` (the ground truth's search structure, where the tree builds it apart), ``silhouettes``
  (hard renders and mask IoU), ``own-mean forward`` (the model's pass computing its own mean shapes), ``rest``
  (the model's forward pass and soft render, colours, tables);
- apart, once per process: the mean shape's fit, and a warm-up (a small ICP before the timed evaluation: compiled
  kernels loaded, thread pools started);
- ``total`` (wall) and ``total cpu``, the speed-ups of this tree's totals over each revision's, and the largest
  relative difference of the mean metrics. The mean shape's fit (once per evaluation, before it) is shown apart.

``--ref`` may be given several times: each revision is a column, this tree the last.

    python benchmarks/bm_eval.py runs/synthetic/checkpoints/last.ckpt --ref main
    python benchmarks/bm_eval.py CKPT --ref v0.1 --ref main --settings heldout,final,full --images 5
    python benchmarks/bm_eval.py CKPT --ref main --device cuda --images 20
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import (  # noqa: E402
    existing_file,
    existing_folder,
    git_revision,
    non_negative_int,
    positive_int,
    require_cuda,
)
from revisions import REPO, child_env, tree_of  # noqa: E402

#: setting -> (surface points, ICP iterations)
SETTINGS = {"heldout": (3000, 10), "final": (50_000, 30), "full": (100_000, 100)}
#: the labels of the successive mesh scorings of a batch, in :func:`unicorn.evaluation.evaluate`'s order
SHAPES = ("model", "mean shape", "own mean")
MEAN_SHAPE_ITERATIONS = 150  # the main job's (held-out and final)


class StageTimer:
    """Exclusive wall time per stage of wrapped functions (a function called inside another is subtracted from
    it); calls inside a *scope* function are keyed ``"<scope label>: <stage>"``."""

    def __init__(self, clock: Callable[[], float], sync: Callable[[], None]) -> None:
        self.clock, self.sync = clock, sync
        self.seconds: dict[str, float] = defaultdict(float)
        self._stack: list[list[float]] = []  # per active call: [time spent in children]
        self._scope: str | None = None
        self._originals: list[tuple[Any, str, Callable]] = []

    def _timed(self, key: Callable[[], str], fn: Callable, *args: Any, **kwargs: Any) -> Any:
        self.sync()
        self._stack.append([0.0])
        t0 = self.clock()
        try:
            return fn(*args, **kwargs)
        finally:
            self.sync()
            elapsed = self.clock() - t0
            children = self._stack.pop()[0]
            self.seconds[key()] += elapsed - children
            if self._stack:
                self._stack[-1][0] += elapsed

    def wrap(self, module: Any, name: str, stage: str) -> None:
        """Time ``module.name`` as ``stage`` (if the module has it)."""
        fn = getattr(module, name, None)
        if fn is None:
            return

        def key() -> str:
            return stage if self._scope is None else f"{self._scope}: {stage}"

        self._originals.append((module, name, fn))
        setattr(module, name, lambda *a, **k: self._timed(key, fn, *a, **k))

    def wrap_scope(self, module: Any, name: str, labels: tuple[str, ...]) -> None:
        """Time ``module.name`` as a scope whose successive calls take the successive ``labels`` (cyclically)."""
        fn = getattr(module, name)
        calls = [0]

        def scoped(*a: Any, **k: Any) -> Any:
            self._scope = labels[calls[0] % len(labels)]
            calls[0] += 1
            try:
                return self._timed(lambda: f"{self._scope}: other", fn, *a, **k)
            finally:
                self._scope = None

        self._originals.append((module, name, fn))
        setattr(module, name, scoped)

    def restore(self) -> None:
        """Put the wrapped functions back."""
        for module, name, fn in reversed(self._originals):
            setattr(module, name, fn)
        self._originals = []


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """In the child: the stage times (seconds) of one evaluation per setting, with the tree on ``sys.path``."""
    import torch

    import unicorn.evaluation.evaluator as evaluator
    import unicorn.metrics.mesh_evaluator as mesh_evaluator
    from unicorn.evaluation import (
        EvalOptions,
        build_eval_dataset,
        evaluate,
        fit_mean_shape,
        protocol_for,
        training_point_clouds,
    )
    from unicorn.io import load_model
    from unicorn.metrics import gradient_icp

    device = torch.device(args.device)
    model, info = load_model(args.checkpoint, map_location=device)
    run_data = info.dataset or {}
    name = args.dataset or run_data.get("name") or "synthetic"
    root = args.root
    if root is None:
        from unicorn.data import dataset_root

        root = str(dataset_root(name, run_data.get("root"), run_data.get("categories"), run_data.get("synthetic")))
    categories = run_data.get("categories")
    data = build_eval_dataset(
        name, root, args.split, img_size=model.config["image_size"], categories=categories, max_images=args.images
    )
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    # stages in CPU time on the CPU (all threads; what other load on the machine changes least), else wall time
    clock = time.perf_counter if device.type == "cuda" else time.process_time
    out: dict[str, Any] = {"unicorn": str(Path(evaluator.__file__).parents[1])}
    # a process's one-time costs (compiled kernels loaded, thread pools started), shown apart from the per-image ones
    t0 = clock()
    gradient_icp(torch.rand(1, 300, 3, device=device), torch.rand(1, 400, 3, device=device), n_iter=3)
    sync()
    warm_up = clock() - t0
    for setting in args.settings:
        num_points, icp_iterations = SETTINGS[setting]
        # the clouds as the held-out callback (its num_points) and unicorn-eval (5000) read them
        clouds = training_point_clouds(root, categories, max_models=200, num_points=min(num_points, 5000))
        t0 = clock()
        mean_shape = fit_mean_shape(
            model.template.verts, model.template.faces, clouds, iterations=args.mean_shape_iterations
        )
        fit = clock() - t0
        options = EvalOptions(
            protocol=protocol_for(name),
            num_points=num_points,
            icp_iterations=icp_iterations,
            average_texture=info.average_texture,
            report_samples=0,
            progress=False,
            own_mean_shape=True,
        )
        timer = StageTimer(clock, sync)
        timer.wrap(mesh_evaluator, "sample_points_from_meshes", "sampling")
        timer.wrap(mesh_evaluator, "gradient_icp", "ICP")
        timer.wrap(mesh_evaluator, "point_cloud_scores", "Chamfer")
        try:
            import unicorn.evaluation.measurements as measures
        except ImportError:  # a tree whose loop makes its measurements itself
            measures = evaluator
        timer.wrap(measures, "_gt_indices", "gt search index")
        for module in {evaluator, measures}:
            timer.wrap(module, "hard_render", "silhouettes")
        timer.wrap(measures, "mask_iou", "silhouettes")
        timer.wrap(evaluator, "_own_mean_shapes", "own-mean forward")
        timer.wrap_scope(measures, "_mesh_scores", SHAPES)
        try:
            sync()
            wall, cpu = time.perf_counter(), time.process_time()
            result = evaluate(model, data, options, name, device=device, shape_baseline=mean_shape)
            sync()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        finally:
            timer.restore()
        stages = dict(timer.seconds)
        stages["rest"] = (wall if device.type == "cuda" else cpu) - sum(stages.values())
        out[setting] = {
            "clock": "wall" if device.type == "cuda" else "cpu",
            "images": len(result.per_image),
            "stages": stages,
            "total": wall,
            "total cpu": cpu,
            "fit": fit,
            "warm-up": warm_up,
            "means": {k: v for k, v in result.mean.items() if k in result.columns},
        }
    return out


def run_child(tree: Path, args: argparse.Namespace, setting: str, workdir: Path) -> dict[str, Any]:
    """``measure`` in a fresh process importing ``tree``'s ``unicorn``."""
    out = workdir / f"{abs(hash((str(tree), setting)))}.json"
    cmd = [sys.executable, __file__, "--child", str(out), args.checkpoint, "--settings", setting]
    for option in ("root", "dataset", "split", "images", "device", "mean_shape_iterations"):
        value = getattr(args, option)
        if value is not None:
            cmd += [f"--{option.replace('_', '-')}", str(value)]
    proc = subprocess.run(cmd, env=child_env(tree, args.threads), capture_output=True, text=True)
    if proc.returncode != 0 or not out.exists():
        sys.exit(f"bm_eval.py: error: the evaluation in {tree} failed:\n{proc.stderr[-3000:]}")
    return json.loads(out.read_text())


def stage_order(names: set[str]) -> list[str]:
    """Per-shape stages first (model, mean shape, own mean), then the others, ``rest`` last."""
    per_shape = [f"{s}: {k}" for s in SHAPES for k in ("sampling", "ICP", "Chamfer", "other")]
    others = ["gt search index", "silhouettes", "own-mean forward"]
    known = per_shape + others + ["rest"]
    return [n for n in known if n in names] + sorted(names - set(known))


def report(setting: str, results: dict[str, dict[str, Any]]) -> None:
    """Print one setting's table: ms per image per stage for every variant, and the speed-ups."""
    num_points, icp_iterations = SETTINGS[setting]
    first = next(iter(results.values()))
    print(f"\n# {setting}: {num_points} points, {icp_iterations} ICP iterations, {first['images']} images")
    names = list(results)
    print(f"{'ms per image (' + first['clock'] + ')':28s}" + "".join(f"{n[:22]:>24s}" for n in names))
    stages = stage_order({k for r in results.values() for k in r["stages"]})
    for stage in stages:
        cells = []
        for r in results.values():
            v = r["stages"].get(stage)
            cells.append(f"{1000 * v / r['images']:24.1f}" if v is not None else f"{'-':>24s}")
        print(f"{stage:28s}" + "".join(cells))
    for key in ("total", "total cpu"):
        print(f"{key:28s}" + "".join(f"{1000 * r[key] / r['images']:24.1f}" for r in results.values()))
    print(f"{'mean-shape fit (once), ms':28s}" + "".join(f"{1000 * r['fit']:24.1f}" for r in results.values()))
    print(f"{'warm-up (once), ms':28s}" + "".join(f"{1000 * r['warm-up']:24.1f}" for r in results.values()))
    mine = results[names[-1]]
    for name in names[:-1]:
        wall = results[name]["total"] / mine["total"]
        cpu = results[name]["total cpu"] / mine["total cpu"]
        print(f"speed-up of {names[-1]} over {name}: {wall:.2f}x wall, {cpu:.2f}x cpu")
    for name in names[:-1]:
        a, b = results[name]["means"], mine["means"]
        diffs = {k: abs(a[k] - b[k]) / max(abs(a[k]), 1e-12) for k in a if k in b and a[k] == a[k]}
        worst = max(diffs, key=diffs.get) if diffs else None
        if worst is not None:
            print(f"largest relative difference of the mean metrics from {name}: {worst} {diffs[worst]:.1e}")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "checkpoint",
        type=existing_file,
        help="a trained checkpoint (unicorn-train .ckpt or unicorn.io.save_model file)",
    )
    parser.add_argument(
        "--ref",
        type=git_revision,
        action="append",
        default=[],
        help="git revision to compare with (repeatable: one column each)",
    )
    parser.add_argument("--settings", default="heldout,full", help="comma-separated, of " + ", ".join(SETTINGS))
    parser.add_argument("--images", type=positive_int, default=3, help="test images scored (default: 3)")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="(default: cpu)")
    parser.add_argument(
        "--threads", type=positive_int, default=None, help="OMP_NUM_THREADS of the runs (default: torch's)"
    )
    parser.add_argument("--dataset", default=None, help="dataset name (default: the checkpoint's training run's)")
    parser.add_argument(
        "--root", type=existing_folder, default=None, help="dataset root (default: the checkpoint's training run's)"
    )
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--mean-shape-iterations", type=non_negative_int, default=MEAN_SHAPE_ITERATIONS)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.settings = [s.strip() for s in args.settings.split(",") if s.strip()]
    if (unknown := [s for s in args.settings if s not in SETTINGS]) or not args.settings:
        parser.error(f"--settings: unknown {unknown}; choose from {list(SETTINGS)}")
    if args.child is None:  # the parent checks what it can before any evaluation
        require_cuda(parser, args.device)
        if args.dataset is not None:
            from unicorn.data import DATASET_NAMES  # this tree's names (the children import their own)

            if args.dataset not in DATASET_NAMES:
                parser.error(f"--dataset: unknown {args.dataset!r}; known: {', '.join(DATASET_NAMES)}")
    return args


def check_checkpoint(path: str) -> None:
    """End the script in one line, before any child starts, when ``path`` does not hold a UNICORN model."""
    from unicorn.errors import UserError
    from unicorn.io import load_model

    try:
        load_model(path, map_location="cpu")
    except (UserError, OSError) as err:
        sys.exit(f"bm_eval.py: error: {err}")


def main() -> None:
    args = parse_args()
    if args.child:
        Path(args.child).write_text(json.dumps(measure(args)), encoding="utf-8")
        return
    check_checkpoint(args.checkpoint)
    variants = {**{ref: tree_of(ref) for ref in args.ref}, "this tree": REPO}
    print(f"# evaluation cost per image: {args.checkpoint}, {args.split} split, device {args.device}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bm_eval-") as tmp:
        for setting in args.settings:
            results = {}
            for name, tree in variants.items():
                results[name] = run_child(tree, args, setting, Path(tmp))[setting]
                print(f"  {setting} {name}: {results[name]['total'] / results[name]['images']:.2f} s/image", flush=True)
            report(setting, results)


if __name__ == "__main__":
    main()
