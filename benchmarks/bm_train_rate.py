"""Iterations per second of the README main job's training loop, this tree against an earlier commit.

Runs ``unicorn-train experiment=synthetic`` (the main job's data, model, schedule and callbacks) for
``--steps`` iterations in fresh processes, alternating the variants so that a busy machine slows both alike,
and reports for each variant the median over ``--repeats`` runs of

- ``it/s``: iterations per second of wall time between iteration ``--warmup`` and the last one (everything the
  trainer does in between counts: logging, checkpoints, image logging, held-out scoring if enabled);
- ``cpu ms/it``: the process's CPU time per iteration over the same window (less sensitive to other load;
  with more than one thread it includes the threads' spinning; under ``trainer=ddp_cpu``, rank 0's process only);
- a line per variant with that CPU time thread by thread, the busiest first (Linux: ``/proc``; the median run's):
  ``main`` runs the loop and launches the forward, ``pt_autograd_<device>`` the backward on CUDA, the intra-op
  pool's threads (the process's name) share the CPU's kernels.

``--ref REV`` adds the tree of git revision REV (checked out once with ``git worktree`` under the system's
temporary folder) as the "before" variant; ``--variant "NAME OVERRIDE..."`` (one quoted argument, split like
a shell line) adds this tree with more Hydra overrides (repeatable). Extra arguments are Hydra overrides for
every variant.

    python benchmarks/bm_train_rate.py --ref main                          # this tree against main, held-out off
    python benchmarks/bm_train_rate.py --ref main --heldout                # with the main job's held-out scoring
    python benchmarks/bm_train_rate.py --variant "width-32 model.encoder.width=32" 'schedule.milestones=[20,40,60]'
    python benchmarks/bm_train_rate.py --steps 200 trainer=gpu             # on CUDA, as users train there
    python benchmarks/bm_train_rate.py --variant "sync-free optim.sync_free=true"   # the CUDA step path, on the CPU
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import git_revision, non_negative_int, positive_int  # noqa: E402
from revisions import REPO, child_env, tree_of  # noqa: E402


def make_timer_callback(out: str, warmup: int):  # noqa: ANN201
    """A Lightning callback (instantiated by Hydra in the child) that times iterations ``warmup`` .. the end."""
    from lightning.pytorch.callbacks import Callback

    class IterationTimer(Callback):
        def __init__(self) -> None:
            self.start: tuple[float, float, int] | None = None
            self.threads: dict[int, tuple[str, float]] = {}

        def on_train_batch_start(self, trainer, module, batch, batch_idx) -> None:  # noqa: ANN001
            if self.start is None and trainer.global_step >= warmup:
                self.start = (time.perf_counter(), time.process_time(), trainer.global_step)
                self.threads = thread_cpu_times()

        def on_train_end(self, trainer, module) -> None:  # noqa: ANN001
            if self.start is None:  # an override ended training early (trainer.max_steps)
                raise RuntimeError(f"training ended at iteration {trainer.global_step}, before --warmup {warmup}")
            wall, cpu, step = self.start
            n = trainer.global_step - step
            result = {"iterations": n, "wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}
            result["threads"] = cpu_by_thread(self.threads, thread_cpu_times())
            Path(out).write_text(json.dumps(result), encoding="utf-8")

    return IterationTimer()


def thread_cpu_times() -> dict[int, tuple[str, float]]:
    """This process's threads: id -> (name, CPU seconds so far, user and system); empty where ``/proc`` is not."""
    stats = list(Path("/proc/self/task").glob("*/stat"))
    tick = os.sysconf("SC_CLK_TCK") if stats else 0
    times = {}
    for stat in stats:
        try:
            text = stat.read_text()
        except OSError:  # the thread ended meanwhile
            continue
        name, fields = text[text.index("(") + 1 : text.rindex(")")], text[text.rindex(")") + 2 :].split()
        times[int(stat.parent.name)] = (name, (int(fields[11]) + int(fields[12])) / tick)  # utime, stime
    return times


def cpu_by_thread(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]]) -> list:
    """CPU seconds of each thread between two :func:`thread_cpu_times`, as ``[name, seconds]``, most first; the
    process's main thread named ``main`` (a thread started in between counts from 0, one that ended is not seen)."""
    used = [
        ["main" if tid == os.getpid() else name, seconds - (before[tid][1] if tid in before else 0.0)]
        for tid, (name, seconds) in after.items()
    ]
    return sorted(used, key=lambda item: -item[1])


def experiment_override(tree: Path) -> str:
    """``experiment=synthetic``, or ``+experiment=synthetic`` for trees from before ``experiment: null``."""
    grouped = "experiment: null" in (tree / "conf" / "train.yaml").read_text()
    return ("" if grouped else "+") + "experiment=synthetic"


def run_once(tree: Path, args: argparse.Namespace, overrides: list[str], workdir: Path) -> dict:
    """Train in ``tree`` with ``overrides`` in a fresh process; its timer's figures."""
    out = workdir / "timing.json"
    env = child_env(tree, args.threads)
    cmd = [
        sys.executable,
        "-m",
        "unicorn.cli.train",
        experiment_override(tree),
        f"trainer.max_steps={args.steps}",
        "evaluate.enabled=false",
        "trainer.enable_progress_bar=true",
        f"hydra.run.dir={workdir / 'run'}",
        "+callbacks.extra.timer._target_=bm_train_rate.make_timer_callback",
        f"+callbacks.extra.timer.out={out}",
        f"+callbacks.extra.timer.warmup={args.warmup}",
        *([] if args.heldout else ["callbacks.heldout=null"]),
        *overrides,
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0 or not out.exists():
        sys.exit(f"bm_train_rate.py: error: training in {tree} failed:\n{proc.stderr[-3000:]}")
    return json.loads(out.read_text())


def parse_args(argv: list[str] | None = None) -> tuple[argparse.Namespace, list[str]]:
    """The options and the Hydra overrides of every variant; ``args.variant`` is a list of (name, overrides)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--ref", type=git_revision, default=None, help="git revision to compare with (the 'before' variant)"
    )
    parser.add_argument("--steps", type=positive_int, default=400, help="training iterations of each run")
    parser.add_argument(
        "--warmup",
        type=non_negative_int,
        default=None,
        help="iterations before the timing, below --steps (default: 50, or half of a shorter --steps)",
    )
    parser.add_argument("--repeats", type=positive_int, default=2, help="runs per variant (the median is printed)")
    parser.add_argument(
        "--threads", type=positive_int, default=None, help="OMP_NUM_THREADS of the runs (default: torch's)"
    )
    parser.add_argument("--heldout", action="store_true", help="keep the main job's held-out scoring")
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar='"NAME OVERRIDE..."',
        help="also run this tree with these Hydra overrides, named NAME (one quoted argument; repeatable)",
    )
    args, overrides = parser.parse_known_args(argv)
    if args.warmup is None:
        args.warmup = min(50, args.steps // 2)
    elif args.warmup >= args.steps:
        parser.error(f"--warmup must be below --steps ({args.steps}), got {args.warmup}")
    if unknown := [o for o in overrides if o.startswith("-")]:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    variants = []
    for spec in args.variant:
        # one argument per variant: a bare list of overrides would swallow the overrides meant for every variant
        parts = shlex.split(spec)
        if len(parts) < 2 or parts[0] in ("this tree", *(n for n, _ in variants)):
            parser.error(f"--variant {spec!r}: needs a new name and at least one override, in one quoted argument")
        variants.append((parts[0], parts[1:]))
    args.variant = variants
    return args, overrides


def main() -> None:
    args, overrides = parse_args()
    # name -> (tree, the variant's own overrides)
    variants: dict[str, tuple[Path, list[str]]] = {"this tree": (REPO, [])}
    if args.ref:
        variants = {f"before ({args.ref})": (tree_of(args.ref), []), **variants}
    variants.update((name, (REPO, extra)) for name, extra in args.variant)
    results: dict[str, list[dict]] = {name: [] for name in variants}
    with tempfile.TemporaryDirectory(prefix="bm_train_rate-") as tmp:
        for r in range(args.repeats):
            for name, (tree, extra) in variants.items():
                workdir = Path(tmp) / f"{len(results[name])}-{abs(hash(name))}"
                results[name].append(run_once(tree, args, [*overrides, *extra], workdir))
                last = results[name][-1]
                print(f"  run {r + 1}/{args.repeats} {name}: {last['iterations'] / last['wall']:.2f} it/s", flush=True)
    threads = args.threads or "torch default"
    print(f"# main job training rate: experiment=synthetic, iterations {args.warmup}..{args.steps}, threads {threads}")
    print(f"{'variant':28s} {'it/s':>8s} {'cpu ms/it':>10s}")
    rates = {}
    for name, rows in results.items():
        rates[name] = statistics.median(r["iterations"] / r["wall"] for r in rows)
        cpu = statistics.median(1000 * r["cpu"] / r["iterations"] for r in rows)
        print(f"{name:28s} {rates[name]:8.2f} {cpu:10.1f}")
    for name, rows in results.items():
        median = sorted(rows, key=lambda r: r["iterations"] / r["wall"])[len(rows) // 2]
        busy = [(t, 1000 * s / median["iterations"]) for t, s in median["threads"] if s > 0]
        shown = ", ".join(f"{t} {ms:.1f}" for t, ms in busy[:6]) + (f", {len(busy) - 6} more" if len(busy) > 6 else "")
        print(f"# {name}: cpu ms/it by thread: {shown or 'not measured here (no /proc)'}")
    first, *others = rates
    for name in others:
        print(f"speed-up of {name} over {first}: {rates[name] / rates[first]:.2f}x")


if __name__ == "__main__":
    main()
