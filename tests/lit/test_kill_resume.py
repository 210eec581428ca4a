"""Fault injection: a tiny training killed (SIGKILL) at random points, also inside checkpoint writes, and resumed
each time ends bitwise equal to an uninterrupted run, with the same metric log and no leftover files.

The kill points are drawn from ``UNICORN_FAULT_SEED`` (default: a new seed per run, printed on failure), so that
CI explores different interleavings over time while a failure can be replayed.
"""

from __future__ import annotations

import csv
import os
import random
import signal
import time
from pathlib import Path

import torch

from tests.support import forked
from tests.support.training import TINY

MAX_STEPS = 6
EVERY = 3  # checkpoint period: step=3 and step=6 (each with last.ckpt, a second name of it)
OVERRIDES = [
    *[a for a in TINY if not a.startswith(("logger=", "callbacks.heldout="))],
    "logger=default",  # TensorBoard and CSV
    f"trainer.max_steps={MAX_STEPS}",
    f"callbacks.checkpoint.every_n_steps={EVERY}",
    "callbacks.checkpoint.keep=1",
    # rows logged by callbacks at the checkpoints' iterations, before and after the checkpoint is written
    f"+callbacks.heldout={{every_n_steps:{EVERY},max_images:2,num_points:100,icp_iterations:1,shape_points:0}}",
    f"callbacks.diagnostics.every_n_steps={EVERY}",
]


def _train(out: str, extra: list[str]) -> None:  # runs in a forked child
    from tests.support.training import compose_config
    from unicorn.lit.run import build, fit

    fit(build(compose_config([*OVERRIDES, f"paths.output_dir={out}", *extra])))
    os._exit(0)


def _attempt(out: Path, *extra: str) -> int:
    """Train in a new process; returns its exit code (-9: killed)."""
    process = forked.context().Process(  # a cheap fork of a server with torch imported
        target=_train, args=(str(out), list(extra))
    )
    process.start()
    process.join(timeout=300)
    if process.exitcode is None:
        process.kill()
        raise TimeoutError(f"training in {out} with {extra} did not end in 300 s")
    return process.exitcode


def _kill_plan(rng: random.Random) -> list[tuple[int, str, int]]:
    """Three kills at increasing iterations (so that every attempt gets past the checkpoint it resumed from),
    at least one of them inside a checkpoint write; ``(iteration, where, nth write)``."""
    write_step = rng.choice(range(EVERY, MAX_STEPS + 1, EVERY))
    others = rng.sample([s for s in range(1, MAX_STEPS + 1) if s != write_step], 2)
    plan = []
    for step in sorted([write_step, *others]):
        where = (
            "write" if step == write_step else rng.choice(["iteration", "write"]) if step % EVERY == 0 else "iteration"
        )
        # a periodic save writes one file (last.ckpt is a second name of it, made in microseconds)
        plan.append((step, where, 1))
    return plan


def _scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    """What TensorBoard shows: every scalar's (step, value) series, after its purge events are applied."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def _rows(run: Path) -> list[dict[str, str]]:
    with open(run / "csv" / "metrics.csv", encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))


def _key(row: dict[str, str]) -> tuple[tuple[str, str], ...]:
    return tuple(sorted((k, v) for k, v in row.items() if v))


def test_killed_and_resumed_run_equals_an_uninterrupted_one(synthetic_cache, tmp_path):
    seed = int(os.environ.get("UNICORN_FAULT_SEED", time.time_ns() % 2**31))
    plan = _kill_plan(random.Random(seed))
    context = f"UNICORN_FAULT_SEED={seed}, kills (iteration, where, nth write): {plan}"

    straight = tmp_path / "straight"
    assert _attempt(straight) == 0
    killed = tmp_path / "killed"
    for step, where, nth in plan:
        kill = f"+callbacks.extra.kill={{_target_:tests.lit.faults.Kill,step:{step},where:{where},nth_write:{nth}}}"
        code = _attempt(killed, "ckpt_path=last", kill)
        assert code == -signal.SIGKILL, f"{context}: the attempt killed at {step} exited with {code}"
    assert _attempt(killed, "ckpt_path=last") == 0, context

    a = torch.load(straight / "checkpoints" / "last.ckpt", weights_only=True)
    b = torch.load(killed / "checkpoints" / "last.ckpt", weights_only=True)
    assert a["global_step"] == b["global_step"] == MAX_STEPS
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for key, value in a["state_dict"].items():
        assert torch.equal(value, b["state_dict"][key]), f"{context}: {key} differs"
    for index, state in a["optimizer_states"][0]["state"].items():
        for name, value in state.items():
            assert torch.equal(value, b["optimizer_states"][0]["state"][index][name]), f"{context}: adam {name}"
    memory_a, memory_b = a["unicorn"]["ranks"][0]["memory"], b["unicorn"]["ranks"][0]["memory"]
    for key, value in memory_a.items():
        assert (value is None and memory_b[key] is None) or torch.equal(value, memory_b[key]), context
    # the metric log reads as one run's: every iteration once, with the uninterrupted run's values, the callbacks'
    # rows at the checkpoints' iterations included, and each row whole (both step kinds' latest losses)
    rows_a, rows_b = _rows(straight), _rows(killed)
    assert sorted(map(_key, rows_b)) == sorted(map(_key, rows_a)), context
    # TensorBoard: the earlier attempts' event files stay, the repeated iterations count once
    assert len(list((killed / "tensorboard").glob("events.out.tfevents.*"))) == len(plan) + 1, context
    scalars_a, scalars_b = _scalars(straight), _scalars(killed)
    assert scalars_b.keys() == scalars_a.keys() and scalars_a, context
    for tag, series in scalars_b.items():
        steps = [step for step, _ in series]
        assert steps == sorted(set(steps)), f"{context}: {tag} repeats steps {steps}"
        assert set(series) <= set(scalars_a[tag]), f"{context}: {tag} {series} vs {scalars_a[tag]}"
    logged_steps = [{step for series in scalars.values() for step, _ in series} for scalars in (scalars_a, scalars_b)]
    assert logged_steps[0] == logged_steps[1], context
    # no partial checkpoint left, and rotation kept `keep` periodic files across the attempts
    names = sorted(p.name for p in (killed / "checkpoints").iterdir())
    assert names == ["last.ckpt", "step=0000006.ckpt"], f"{context}: {names}"
