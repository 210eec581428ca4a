"""A refused or interrupted command never deletes, overwrites or half-writes anything (issue 61's probe).

Each refusal is checked for its exit status, its one line on stderr, and that every file present before the
command is byte-identical after it (and that nothing was added or removed). The signal tests stop a real
``unicorn-train`` and resume from the ``last.ckpt`` it wrote.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from tests.support.signals import SignalAtCall
from tests.support.training import TINY, error_lines, snapshot, unicorn_train

#: a refusal that happens once the folder was accepted, while the trainer is built
LATE_FAILURE = "trainer.devices=0"


@pytest.fixture(scope="module")
def finished_run(synthetic_cache, tmp_path_factory) -> Path:
    """A finished tiny run: ``step=0000004.ckpt``, ``step=0000008.ckpt``, ``last.ckpt`` (iteration 8)."""
    run = tmp_path_factory.mktemp("finished") / "run"
    result = unicorn_train(*TINY, f"hydra.run.dir={run}", cwd=run.parent)
    assert result.returncode == 0, result.stderr[-3000:]
    return run


def _users_folder(tmp_path: Path, finished_run: Path, kind: str) -> Path:
    """The folder a case runs in, as the user left it."""
    folder = tmp_path / "myproj"
    if kind.startswith("finished"):
        shutil.copytree(finished_run, folder)
        if kind == "finished-truncated-provenance":
            record = folder / "provenance.json"
            record.write_bytes(record.read_bytes()[:40])  # cut off mid-record, as by a full disk
    elif kind == "cwd":
        folder = tmp_path  # hydra.run.dir=. : the directory the user works in
        (folder / "notes.txt").write_text("mine")
    else:
        folder.mkdir()
        for name in kind.split("+") if kind != "empty" else []:
            target = folder / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(f"the user's {name}\n")
    return folder


#: (id, what the folder holds, overrides, the error's pattern)
TRAIN_CASES = [
    ("users-config", "config.yaml", [], r"holds config\.yaml but no run"),
    ("users-hydra-record", ".hydra/config.yaml", [], r"holds \.hydra but no run"),
    # ckpt_path=last (a requeued job's) trains a run killed before its first checkpoint again, not over a user's file
    ("users-config-resumed", "config.yaml", ["ckpt_path=last"], r"holds config\.yaml but no run; .*overwrite=true$"),
    ("empty-folder-late-failure", "empty", [LATE_FAILURE], r"devices=0"),
    ("log-only-late-failure", "train.log", [LATE_FAILURE], r"devices=0"),
    ("cwd-late-failure", "cwd", [LATE_FAILURE], r"devices=0"),
    ("new-run-over-a-run", "finished", [], r"already holds a run \(checkpoints/last\.ckpt\)"),
    ("refused-resume", "finished", ["ckpt_path=last", LATE_FAILURE], r"devices=0"),
    (
        "resume-from-an-earlier-checkpoint",
        "finished",
        ['ckpt_path="{run}/checkpoints/step=0000004.ckpt"', "trainer.max_steps=12"],
        r"would delete or replace the later checkpoints checkpoints/step=0000008\.ckpt, checkpoints/last\.ckpt; "
        r"pass overwrite=true",
    ),
    (
        "resume-with-a-truncated-provenance",
        "finished-truncated-provenance",
        ["ckpt_path=last", "trainer.max_steps=12"],
        r"myproj/provenance\.json is not the list of this run's starts \(Unterminated string .*\); repair it",
    ),
]


def _assert_one_error_line(result: subprocess.CompletedProcess, message: str) -> None:
    """Exit status 2 and one stderr line, ``unicorn-train: error: ...``, matching ``message``."""
    lines = error_lines(result.stderr)
    assert result.returncode == 2, result.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("unicorn-train: error: "), lines
    assert re.search(message, lines[0]), lines


@pytest.mark.parametrize("run_dir", ["notes.txt", "notes.txt/run"])
@pytest.mark.parametrize("sweep", [False, True])
def test_a_run_folder_that_is_a_file_is_named(tmp_path, run_dir, sweep):
    (tmp_path / "notes.txt").write_text("the user's notes\n")
    key = "hydra.sweep.dir" if sweep else "hydra.run.dir"
    result = unicorn_train(*(["-m", "seed=1,2"] if sweep else []), *TINY, f"{key}={run_dir}", cwd=tmp_path)
    inside = "is a file" if run_dir == "notes.txt" else f"is inside {tmp_path / 'notes.txt'}, which is a file"
    _assert_one_error_line(
        result, re.escape(f"the run folder {tmp_path / run_dir} {inside}: choose another folder ({key}=...)")
    )
    assert (tmp_path / "notes.txt").read_text() == "the user's notes\n" and sorted(os.listdir(tmp_path)) == [
        "notes.txt"
    ]


@pytest.mark.parametrize("kind, overrides, message", [c[1:] for c in TRAIN_CASES], ids=[c[0] for c in TRAIN_CASES])
def test_a_refused_run_leaves_the_folder_as_it_was(finished_run, tmp_path, kind, overrides, message):
    folder = _users_folder(tmp_path, finished_run, kind)
    before = snapshot(folder)
    run_dir = "." if kind == "cwd" else str(folder)
    args = [o.format(run=folder) for o in overrides]
    result = unicorn_train(*TINY, *args, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    _assert_one_error_line(result, message)
    assert folder.is_dir() and snapshot(folder) == before


#: (id, overrides, the error's pattern): refused while the config is checked, before any folder is made
SETTING_CASES = [
    ("img-size-not-the-datas", ["dataset.img_size=64"], r"dataset\.img_size=64, but the synthetic images are 32 px"),
    ("devices-negative", ["trainer.devices=-3"], r"trainer\.devices must be 'auto', a number of devices .*got -3$"),
    ("devices-text", ["trainer.devices=abc"], r"trainer\.devices must be .*got 'abc'$"),
    ("seed-negative", ["seed=-5"], r"seed must be a whole number in \[0, 4294967295\] \(numpy's seeds\), got -5$"),
    ("seed-huge", ["seed=4294967296"], r"seed must be a whole number in \[0, 4294967295\].*got 4294967296$"),
    ("precision", ["trainer.precision=bogus"], r"trainer\.precision must be one of \(.*'32-true'.*\), got 'bogus'$"),
    ("strategy", ["trainer.strategy=bogus"], r"trainer\.strategy must be one of \['auto', 'ddp'.*got 'bogus'$"),
    (  # Lightning's plain DDP: every process stopped at the first step, the run's folder written
        "devices-two-strategy-auto",
        ["trainer.accelerator=cpu", "trainer.devices=2"],
        r"trainer\.strategy=auto with trainer\.devices=2 runs Lightning's plain DDP, .* use "
        r"trainer\.strategy=ddp_find_unused_parameters_true \(as trainer=ddp and trainer=ddp_cpu do\), or one device "
        r"\(trainer\.devices=1\)$",
    ),
    (
        "background-color",
        ["renderer.background_color=[2,3]"],
        r"renderer\.background_color must be three numbers in \[0, 1\] \(RGB\), got \[2, 3\]$",
    ),
    (
        "azim-range-reversed",
        ["model.pose.azim_range=[360,0]"],
        r"model\.pose\.azim_range must be two finite numbers \[min, max\] with min <= max, got \[360\.0, 0\.0\]$",
    ),
    (
        "img-size-huge",
        ["dataset.img_size=100000"],
        r"dataset\.img_size=100000 needs 10,000,000,000 pixels .*\(UNICORN_MAX_IMAGE_PIXELS; 0: no limit\)$",
    ),
    (
        "encoder-width-huge",
        ["model.encoder.width=100000"],
        r"model needs [\d,]+ parameters \(.*encoder\.width=100000\), above the limit of 500,000,000 parameters "
        r"\(UNICORN_MAX_MODEL_PARAMS; 0: no limit\)$",
    ),
    (
        "texture-size-huge",
        ["model.texture.size=65536"],
        r"model\.texture\.size=65536 needs 4,294,967,296 pixels .*\(UNICORN_MAX_IMAGE_PIXELS; 0: no limit\)$",
    ),
    (  # scored after training: refused before it, not once the run is done
        "final-points-huge",
        ["evaluate.enabled=true", "evaluate.num_points=20000000"],
        r"evaluate\.num_points=20000000 needs 20,000,000 points \(points sampled on each mesh\), above the limit",
    ),
    (  # the log and .hydra/ went to the run folder, the checkpoints and the CSV elsewhere
        "output-dir-elsewhere",
        ["paths.output_dir=elsewhere"],
        r"paths\.output_dir=\S+elsewhere is not the run's folder \S+, where its log goes: choose the folder with",
    ),
    ("checkpoint-dev-zero", ["ckpt_path=/dev/zero"], r"ckpt_path: /dev/zero is not a regular file"),
    (
        "checkpoint-of-another-model",
        ["model=small", "model.loss.perceptual=structural", 'ckpt_path="{finished}/checkpoints/last.ckpt"'],
        r"ckpt_path: the weights of \S+last\.ckpt do not fit the configured model .*: missing \[",
    ),
]


@pytest.mark.parametrize("overrides, message", [c[1:] for c in SETTING_CASES], ids=[c[0] for c in SETTING_CASES])
def test_a_bad_setting_is_one_line_and_writes_nothing(finished_run, tmp_path, overrides, message):
    (tmp_path / "notes.txt").write_text("mine")
    before, finished = snapshot(tmp_path), snapshot(finished_run)
    args = [o.format(finished=finished_run) for o in overrides]
    run = tmp_path / "outputs" / "train" / "runs" / "now"  # as the default run folder in a new project
    result = unicorn_train(*TINY, *args, f"hydra.run.dir={run}", cwd=tmp_path)
    _assert_one_error_line(result, message)
    assert snapshot(tmp_path) == before and snapshot(finished_run) == finished  # no outputs/ left either


def test_a_locked_folder_refuses_a_second_run(finished_run, tmp_path):
    folder = _users_folder(tmp_path, finished_run, "finished")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import pathlib, sys, time; from unicorn.io.run_folder import lock_folder; "
         f"lock_folder(pathlib.Path({str(folder)!r})); print('locked', flush=True); time.sleep(300)"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = snapshot(folder)
        result = unicorn_train(*TINY, "ckpt_path=last", f"hydra.run.dir={folder}", cwd=tmp_path)
        lines = error_lines(result.stderr)
        assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
        assert f"is in use by another unicorn-train (pid {holder.pid} on " in lines[0], lines
        assert snapshot(folder) == before
    finally:
        holder.kill()
        holder.wait()


def test_last_without_last_ckpt_resumes_from_the_newest_step_file(finished_run, tmp_path):
    folder = _users_folder(tmp_path, finished_run, "finished")
    (folder / "checkpoints" / "last.ckpt").unlink()
    steps = {p.name: p.read_bytes() for p in (folder / "checkpoints").glob("step=*.ckpt")}
    result = unicorn_train(
        *TINY, "ckpt_path=last", "callbacks.checkpoint.save_last=false", "trainer.max_steps=10",
        f"hydra.run.dir={folder}", cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert "resuming from the newest checkpoint" in (folder / "train.log").read_text()
    assert "training from scratch" not in (folder / "train.log").read_text()
    after = {p.name: p.read_bytes() for p in (folder / "checkpoints").glob("step=*.ckpt")}
    assert after["step=0000008.ckpt"] == steps["step=0000008.ckpt"]  # resumed from, kept
    # the end of training is a step file of its own (no last.ckpt); the rotation keeps the newest two
    assert sorted(after) == ["step=0000008.ckpt", "step=0000010.ckpt"]
    assert torch.load(folder / "checkpoints" / "step=0000010.ckpt", weights_only=True)["global_step"] == 10


def test_eval_refuses_a_non_empty_out(tmp_path):
    from tests.support.evaluation import tiny_checkpoint

    checkpoint = tiny_checkpoint(tmp_path / "model.pt")
    out = tmp_path / "results"
    out.mkdir()
    (out / "metrics.csv").write_text("the user's table\n")
    before = snapshot(out)
    result = subprocess.run(
        [sys.executable, "-m", "unicorn.cli.eval", str(checkpoint), "--dataset", "synthetic", "--root", str(tmp_path),
         "--device", "cpu", "--out", str(out)],
        capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert result.returncode == 2, result.stderr[-3000:]
    assert result.stderr.splitlines() == [
        f"unicorn-eval: error: --out {out} is not empty; choose another folder or pass --overwrite to write into it"
    ]
    assert snapshot(out) == before


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_writes_last_ckpt_and_the_run_resumes(synthetic_cache, tmp_path, signum):
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    args = [*TINY, "trainer.max_steps=100000", "callbacks.checkpoint.every_n_steps=1", "callbacks.checkpoint.keep=1"]
    args += ["callbacks.checkpoint.save_last=false", "logger=csv", f"hydra.run.dir={run}"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "unicorn.cli.train", *args],
        cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 180
        while not list((run / "checkpoints").glob("step=*.ckpt")):  # an iteration has run
            assert proc.poll() is None and time.monotonic() < deadline, "no iteration ran"
            time.sleep(0.2)
        proc.send_signal(signum)
        _, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, stderr[-3000:]
    last_line = stderr.strip().splitlines()[-1]
    pattern = rf"unicorn-train: stopped by {name} after iteration (\d+); \S+last\.ckpt written: .*"
    match = re.fullmatch(pattern, last_line)
    assert match, last_line
    step = int(match.group(1))
    saved = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert saved["global_step"] == step >= 1
    assert not (run / ".unicorn-train.lock").exists()
    # the run's log ends the way the console did
    logged = (run / "train.log").read_text().splitlines()[-1]
    assert logged.endswith(f"[unicorn.train][WARNING] - {last_line.removeprefix('unicorn-train: ')}")
    resumed = unicorn_train(*args, "ckpt_path=last", f"trainer.max_steps={step + 1}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "Restored all states from the checkpoint" in (run / "train.log").read_text()
    newest = run / "checkpoints" / f"step={step + 1:07d}.ckpt"  # save_last=false: the periodic file
    assert torch.load(newest, weights_only=True)["global_step"] == step + 1
    # and the signal's last.ckpt, which whoever reads last.ckpt would take for the run's end, is gone
    assert sorted(p.name for p in (run / "checkpoints").glob("*.ckpt")) == [newest.name]
    # the metric log reads as one run's: every iteration once (TINY logs every iteration)
    with open(run / "csv" / "metrics.csv", encoding="utf-8", newline="") as f:
        logged = [int(row["step"]) for row in csv.DictReader(f) if row.get("train/lr")]
    assert logged == list(range(step + 1)), logged


def test_a_signal_stops_a_sweep_which_the_same_command_in_its_folder_with_ckpt_path_last_finishes(
    synthetic_cache, tmp_path
):
    sweep = tmp_path / "sweep"
    args = [*TINY, "trainer.max_steps=12", "callbacks.checkpoint.every_n_steps=2", f"hydra.sweep.dir={sweep}"]
    args += ["seed=1,2"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "unicorn.cli.train", "-m", *args],
        cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 180
        while not list((sweep / "0" / "checkpoints").glob("step=*.ckpt")):  # the first job has run an iteration
            assert proc.poll() is None and time.monotonic() < deadline, "no iteration ran"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, stderr[-3000:]
    assert error_lines(stderr)[-1].endswith(
        f"; the sweep goes on with the same command and hydra.sweep.dir={sweep} ckpt_path=last"
    ), stderr[-3000:]
    assert not (sweep / "1").exists()  # the sweep stopped with its first job
    ended = subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", "-m", *args, "ckpt_path=last"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert ended.returncode == 0, ended.stderr[-3000:]
    for job in ("0", "1"):
        saved = torch.load(sweep / job / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
        assert saved["global_step"] == 12, job
    assert "Restored all states from the checkpoint" in (sweep / "0" / "train.log").read_text()


def test_a_signal_to_every_ddp_process_stops_them_at_one_iteration_and_the_run_resumes(synthetic_cache, tmp_path):
    """A scheduler's SIGTERM reaches every process of the job: both DDP ranks stop after the same iteration, the
    first one says so once, and the run resumes under DDP from the checkpoint holding both ranks' state."""
    run = tmp_path / "run"
    args = [*TINY, "trainer=ddp_cpu", "callbacks.checkpoint.every_n_steps=1", "callbacks.checkpoint.keep=1"]
    args += [f"hydra.run.dir={run}"]
    with _train_group([*args, "trainer.max_steps=100000"], tmp_path) as proc:
        deadline = time.monotonic() + 240
        while not list((run / "checkpoints").glob("step=*.ckpt")):  # an iteration has run on both ranks
            assert proc.poll() is None and time.monotonic() < deadline, "no iteration ran"
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr[-3000:]
    stops = [line for line in stderr.splitlines() if "stopped by" in line]
    assert len(stops) == 1, stderr[-3000:]
    match = re.fullmatch(
        r"unicorn-train: stopped by SIGTERM after iteration (\d+); \S+last\.ckpt written: .*", stops[0]
    )
    assert match, stops
    step = int(match.group(1))
    saved = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert saved["global_step"] == step >= 1 and len(saved["unicorn"]["ranks"]) == 2
    resumed = unicorn_train(*args, "ckpt_path=last", f"trainer.max_steps={step + 1}", cwd=tmp_path, fresh=True)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "exists and is not empty" not in resumed.stderr  # the folder is the run's own: no alarm
    saved = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert saved["global_step"] == step + 1 and len(saved["unicorn"]["ranks"]) == 2


def test_a_signal_to_every_ddp_process_before_the_first_iteration_stops_them_after_it(synthetic_cache, tmp_path):
    """SIGTERM reaching every DDP rank while rank 0 still sets training up (its held-out scoring's first set-up, say)
    while the others wait for it: no rank hangs; both stop after the first iteration, with its checkpoint."""
    run = tmp_path / "run"
    args = [*TINY, "trainer=ddp_cpu", f"hydra.run.dir={run}", "trainer.max_steps=100000"]
    args += ["+callbacks.extra.signal._target_=tests.support.signals.SignalAtTrainStart"]
    with _train_group(args, tmp_path, PYTHONPATH=os.getcwd()) as proc:  # the callback's module
        _, stderr = proc.communicate(timeout=240)  # every rank ends: none waits on a signal handler's collective
    assert proc.returncode == 143, stderr[-3000:]
    stops = [line for line in stderr.splitlines() if "stopped by" in line]
    last, resume = run / "checkpoints" / "last.ckpt", f"hydra.run.dir={run} ckpt_path=last"
    assert stops == [f"unicorn-train: stopped by SIGTERM after iteration 1; {last} "
                     f"written: the same command with {resume} resumes it"], stderr[-3000:]  # fmt: skip
    saved = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert saved["global_step"] == 1 and len(saved["unicorn"]["ranks"]) == 2


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _disk_full_at_the_second_checkpoint() -> None:
    """unicorn-train's main() on a disk that fills up as ``step=0000008.ckpt`` is flushed (after ``step=0000004.ckpt``
    and its ``last.ckpt``, a second name of it)."""
    from unicorn.cli import train

    fsync = os.fsync

    def full(fd: int) -> None:
        if ".step=0000008.ckpt.tmp-" in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")  # as the kernel reports it: no file named
        fsync(fd)

    os.fsync = full
    train.main()


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="names the written file through /proc")
def test_a_full_disk_while_a_checkpoint_is_written_names_it_keeps_the_others_and_ends_train_log(
    synthetic_cache, tmp_path
):
    run = tmp_path / "run"
    entry = f"{__name__}:_disk_full_at_the_second_checkpoint"
    result = unicorn_train(*TINY, f"hydra.run.dir={run}", cwd=tmp_path, entry=entry)
    assert result.returncode == 2, result.stderr[-3000:]
    second = run / "checkpoints" / "step=0000008.ckpt"
    line = (
        f"error: [Errno 28] No space left on device while writing {second} (the file there before, if any, is as it "
        "was)"
    )
    assert error_lines(result.stderr)[-1] == f"unicorn-train: {line}"
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names == ["last.ckpt", "step=0000004.ckpt"]  # no partial file
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 4
    assert (run / "train.log").read_text().splitlines()[-1].endswith(f"[unicorn.train][ERROR] - {line}")


def _signal_in_the_evaluation() -> None:
    """unicorn-train's main() whose evaluation after training gets SIGTERM (the forked command of the test below)."""
    from unicorn.cli import train
    from unicorn.evaluation import session

    def evaluate_to_folder(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(60)  # not reached: the signal stops the command at once

    session.evaluate_to_folder = evaluate_to_folder
    train.main()


def _signal_in_the_build() -> None:
    """unicorn-train's main() that gets SIGTERM once the run is built, before its first iteration."""
    from unicorn.cli import train
    from unicorn.lit import run as lit_run

    build = lit_run.build

    def signalled(cfg):
        built = build(cfg)
        os.kill(os.getpid(), signal.SIGTERM)
        return built

    lit_run.build = signalled
    train.main()


def _signal_while_the_folder_is_put_back() -> None:
    """unicorn-train's main() whose build fails once the run is built and that gets SIGTERM as it puts the folder
    back."""
    from unicorn.cli import train
    from unicorn.io import run_folder
    from unicorn.lit import run as lit_run

    build, undo = lit_run.build, run_folder.FolderChanges.undo

    def failing(cfg):
        build(cfg)
        raise RuntimeError("a failure after the run's files are written")

    def signalled(self):
        os.kill(os.getpid(), signal.SIGTERM)
        undo(self)

    lit_run.build, run_folder.FolderChanges.undo = failing, signalled
    train.main()


def test_a_signal_in_the_evaluation_after_training_stops_at_once_and_the_run_ends_with_ckpt_path_last(
    synthetic_cache, tmp_path
):
    run = tmp_path / "run"
    args = [*TINY, "evaluate.enabled=true", f"hydra.run.dir={run}"]
    result = unicorn_train(*args, cwd=tmp_path, entry=f"{__name__}:_signal_in_the_evaluation")
    assert result.returncode == 143, result.stderr[-3000:]
    assert error_lines(result.stderr)[-1] == (
        "unicorn-train: stopped by SIGTERM during the evaluation after training; the same command with "
        f"hydra.run.dir={run} ckpt_path=last ends it"
    )
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 8
    assert not (run / ".unicorn-train.lock").exists() and not (run / "eval" / "metrics.csv").exists()
    ended = unicorn_train(*args, "ckpt_path=last", cwd=tmp_path)
    assert ended.returncode == 0, ended.stderr[-3000:]
    assert (run / "eval" / "metrics.csv").is_file()
    # the evaluation records the command as the user gave it, as provenance.json does (none of Hydra's own)
    command = json.loads((run / "provenance.json").read_text())[-1]["command"]
    assert command.startswith("unicorn-train experiment=synthetic ") and command.endswith(" ckpt_path=last")
    produced_by = json.loads((run / "eval" / "metrics.json").read_text())["produced_by"]
    assert produced_by == f"{command} (evaluation after training)"


def test_a_signal_before_the_first_iteration_leaves_the_folder_as_it_was(synthetic_cache, tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("the user's notes\n")
    before = snapshot(folder)
    result = unicorn_train(*TINY, f"hydra.run.dir={folder}", cwd=tmp_path, entry=f"{__name__}:_signal_in_the_build")
    assert result.returncode == 143, result.stderr[-3000:]
    assert error_lines(result.stderr)[-1] == (
        f"unicorn-train: stopped by SIGTERM before the first iteration; {folder} is left as it was"
    )
    assert snapshot(folder) == before


def test_a_signal_while_a_failed_run_puts_the_folder_back_stops_once_it_is_back(synthetic_cache, tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("the user's notes\n")
    before = snapshot(folder)
    result = unicorn_train(
        *TINY, f"hydra.run.dir={folder}", cwd=tmp_path, entry=f"{__name__}:_signal_while_the_folder_is_put_back"
    )
    assert result.returncode == 143, result.stderr[-3000:]
    assert error_lines(result.stderr)[-1] == (
        f"unicorn-train: stopped by SIGTERM before the first iteration; {folder} is left as it was"
    )
    assert snapshot(folder) == before


#: (id, environment or arguments for unicorn-reconstruct on one photo, the error's pattern)
RECONSTRUCT_CASES = [
    ("bbox-nan", {}, ["--bbox", "nan,0,10,10"], r"bbox nan,0,10,10: need four finite numbers"),
    ("bbox-inf", {}, ["--bbox", "0,0,inf,10"], r"bbox 0,0,inf,10: need four finite numbers"),
    ("bbox-outside", {}, ["--bbox", "5000,5000,6000,6000"], r"bbox 5000,5000,6000,6000 does not overlap .*photo\.jpg"),
    ("bbox-huge", {}, ["--bbox", "0,0,1e9,1e9"], r"frames a crop of \d+ x \d+ pixels, above the image limit"),
    ("bbox-overflow", {}, ["--bbox=-1e30,-1e30,1e30,1e30"], r"frames a crop of 2.4e\+30 x 2.4e\+30 pixels, above"),
    # a box starting left of the image, after a space: argparse alone took it for an option
    ("bbox-overflow-spaced", {}, ["--bbox", "-1e30,-1e30,1e30,1e30"], r"frames a crop of 2.4e\+30 x 2.4e\+30 pixels"),
    ("bbox-negative-huge", {}, ["--bbox=-5e18,0,5e18,10"], r"frames a crop of 1.2e\+19 x 1.2e\+19 pixels, above"),
    (
        "bbox-overflow-no-limit",
        {"UNICORN_MAX_IMAGE_BYTES": "0"},
        ["--bbox=-1e30,-1e30,1e30,1e30"],
        r"frames a crop of 2.4e\+30 x 2.4e\+30 pixels, more than any image holds",
    ),
    ("render-bytes-negative", {"UNICORN_MAX_RENDER_BYTES": "-1"}, [], r"UNICORN_MAX_RENDER_BYTES='-1' is not a number"),
    ("render-bytes-text", {"UNICORN_MAX_RENDER_BYTES": "abc"}, [], r"UNICORN_MAX_RENDER_BYTES='abc' is not a number"),
    ("image-pixels-negative", {"UNICORN_MAX_IMAGE_PIXELS": "-5"}, [], r"UNICORN_MAX_IMAGE_PIXELS='-5' is not a number"),
    ("model-params-nan", {"UNICORN_MAX_MODEL_PARAMS": "nan"}, [], r"UNICORN_MAX_MODEL_PARAMS='nan' is not a number"),
    (
        "turntable-frames-huge",
        {},
        ["--turntable-frames", "1000000"],
        r"--turntable-frames 1000000 at --view-size 48 needs 36,864,000,000 bytes \(a turntable's frames: .*\), "
        r"above the limit of 17,179,869,184 bytes \(UNICORN_MAX_RENDER_BYTES; 0: no limit\)$",
    ),
    (
        "strip-views-huge",
        {},
        ["--strip-views", "24", "--view-size", "8192"],
        r"--strip-views 24 at --view-size 8192 needs 25,769,803,776 bytes \(a strip's views: .*\), above the limit",
    ),
    ("refine-huge", {}, ["--refine", "1000000000"], r"--refine 1000000000: steps must be in \[0, 10,000\]"),
    ("padding-huge", {}, ["--padding", "1e9"], r"--padding 1e\+09: must be a finite number in \[0, 10\]"),
    ("padding-nan", {}, ["--padding", "nan"], r"--padding nan: must be a finite number in \[0, 10\]"),
]


@pytest.mark.timeout(120)  # an unbounded turntable or refinement would run for hours
@pytest.mark.parametrize(
    "env, args, message", [c[1:] for c in RECONSTRUCT_CASES], ids=[c[0] for c in RECONSTRUCT_CASES]
)
def test_reconstruct_refuses_a_bad_box_or_limit(tmp_path, capsys, monkeypatch, env, args, message):
    from tests.support.evaluation import tiny_checkpoint, write_inputs
    from unicorn.cli.reconstruct import main

    for name, value in env.items():
        monkeypatch.setenv(name, value)
    checkpoint = tiny_checkpoint(tmp_path / "model.pt")
    write_inputs(tmp_path / "inputs")
    before = snapshot(tmp_path)
    out = tmp_path / "out"
    fast = ["--view-size", "48", "--turntable-frames", "3", "--strip-views", "3", "--quiet", "--device", "cpu"]
    assert main([str(checkpoint), str(tmp_path / "inputs" / "photo.jpg"), "--out", str(out), *fast, *args]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("unicorn-reconstruct: error: "), lines
    assert re.search(message, lines[0]), lines
    assert snapshot(tmp_path) == before  # no output folder, no partial sibling


@pytest.mark.parametrize("option", ["--views", "--size", "--models", "--points"])
def test_synth_refuses_an_empty_dataset(tmp_path, capsys, option):
    from unicorn.cli.data import main

    with pytest.raises(SystemExit) as exit_info:
        main(["synth", "--out", str(tmp_path / "data"), option, "0", "--quiet"])
    assert exit_info.value.code == 2
    last = capsys.readouterr().err.splitlines()[-1]  # after argparse's usage lines
    assert last == f"unicorn-data synth: error: argument {option}: must be a whole number >= 1, got '0'"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", ["-1", "4294967296", "1e30", "1.5", "x"])
@pytest.mark.parametrize("command", ["unicorn-eval", "unicorn-data synth"])
def test_a_seed_outside_numpys_is_a_usage_error(command, value, capsys):
    from unicorn.cli import data, eval

    parser = eval.build_parser() if command == "unicorn-eval" else data.build_parser()
    head = ["model.ckpt"] if command == "unicorn-eval" else ["synth"]
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args([*head, f"--seed={value}"])
    assert exit_info.value.code == 2
    last = capsys.readouterr().err.splitlines()[-1]
    expected = f"argument --seed: must be a whole number in [0, 4294967295] (numpy's seeds), got '{value}'"
    assert last == f"{command}: error: {expected}"


@pytest.mark.parametrize(
    "command, option",
    [("unicorn-eval", "--max-images"), ("unicorn-eval", "--view-size"), ("unicorn-reconstruct", "--batch-size")],
)
def test_whole_number_options_take_the_exponent_form(command, option):
    from unicorn.cli import eval, reconstruct

    parser = eval.build_parser() if command == "unicorn-eval" else reconstruct.build_parser()
    args = parser.parse_args(
        ["model.ckpt", *(["photo.jpg"] if command == "unicorn-reconstruct" else []), option, "1e2"]
    )
    assert getattr(args, option[2:].replace("-", "_")) == 100


def test_reconstruct_overwrite_with_a_file_in_the_way_changes_nothing(tmp_path, capsys):
    from tests.support.evaluation import tiny_checkpoint, write_inputs
    from unicorn.cli.reconstruct import main

    checkpoint = tiny_checkpoint(tmp_path / "model.pt")
    write_inputs(tmp_path / "inputs")  # cutout.png and photo.jpg: outputs in <out>/cutout/ and <out>/photo/
    out = tmp_path / "out"
    out.mkdir()
    (out / "photo").write_text("the user's file, where photo.jpg's folder goes\n")
    before = snapshot(tmp_path)
    fast = ["--view-size", "48", "--turntable-frames", "3", "--strip-views", "3", "--quiet", "--device", "cpu"]
    assert main([str(checkpoint), str(tmp_path / "inputs"), "--out", str(out), "--overwrite", *fast]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and f"{out / 'photo'} is a file where a folder goes" in lines[0], lines
    assert snapshot(tmp_path) == before  # not half-updated: no cutout/, no overview


def test_an_unreadable_limit_in_training_is_one_line_and_leaves_no_folder(synthetic_cache, tmp_path, monkeypatch):
    monkeypatch.setenv("UNICORN_MAX_RENDER_BYTES", "abc")  # read at the first render, inside the first iteration
    run = tmp_path / "run"
    result = unicorn_train(*TINY, f"hydra.run.dir={run}", cwd=tmp_path)
    lines = error_lines(result.stderr)
    assert result.returncode == 2, result.stderr[-3000:]
    # the last line (Lightning may warn about its own deprecations once training starts)
    message = "UNICORN_MAX_RENDER_BYTES='abc' is not a number of bytes >= 0 (0: no limit)"
    assert lines[-1] == f"unicorn-train: error: {message}"
    assert "Traceback" not in result.stderr
    assert not run.exists()


#: (arguments of unicorn-eval, the error's pattern)
EVAL_CASES = [
    (
        ["--num-points", "10000000000"],
        r"--num-points 10000000000 needs 10,000,000,000 points .*above the limit of 10,000,000",
    ),
    (["--num-points", "1e10"], r"--num-points 10000000000 needs 10,000,000,000 points"),
    (["--shape-points", "10000000000"], r"--shape-points 10000000000 needs 10,000,000,000 points"),
    (
        ["--turntable-frames", "100000"],
        r"--turntable-frames 100000 at --view-size \d+ needs 26,214,400,000 bytes "
        r".*\(UNICORN_MAX_RENDER_BYTES; 0: no limit\)$",
    ),
]


@pytest.mark.timeout(120)
@pytest.mark.parametrize("args, message", EVAL_CASES, ids=[" ".join(c[0]) for c in EVAL_CASES])
def test_eval_refuses_a_size_above_its_limit(tmp_path, capsys, args, message):
    from tests.support.evaluation import synthetic_data, tiny_checkpoint
    from unicorn.cli.eval import main

    checkpoint = tiny_checkpoint(tmp_path / "model.pt")
    synthetic_data(tmp_path / "data")
    before = snapshot(tmp_path)
    common = ["--dataset", "synthetic", "--root", str(tmp_path / "data"), "--device", "cpu", "--max-images", "2"]
    assert main([str(checkpoint), *common, "--quiet", "--out", str(tmp_path / "out"), *args]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("unicorn-eval: error: "), lines
    assert re.search(message, lines[0]), lines
    assert snapshot(tmp_path) == before


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["--size", "100000"],
            r"--size 100000 with --supersample 3 needs 90,000,000,000 pixels .*UNICORN_MAX_IMAGE_PIXELS",
        ),
        (["--points", "1e10"], r"--points 10000000000 needs 10,000,000,000 points .*above the limit of 10,000,000"),
        (["--points", "10000000000"], r"--points 10000000000 needs 10,000,000,000 points"),
        # before these bounds, 1e12 models filled the memory until the kernel killed the process
        (["--models", "1e12"], r"--models must be at most 100,000, got 1,000,000,000,000$"),
        (["--models", "100001"], r"--models must be at most 100,000, got 100,001$"),
        (["--views", "1e12"], r"--views must be at most 10,000, got 1,000,000,000,000$"),
        (["--category", ","], r"--category names no category; choose from \['airplane', 'car'"),
    ],
    ids=["size", "points-1e10", "points", "models-1e12", "models", "views", "no-category"],
)
def test_synth_refuses_a_size_above_its_limit(tmp_path, capsys, args, message):
    from unicorn.cli.data import main

    small = [x for option in ("--models", "--views") if option not in args for x in (option, "10")]
    assert main(["synth", "--out", str(tmp_path / "data"), *small, "--quiet", *args]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("unicorn-data: error: "), lines
    assert re.search(message, lines[0]), lines
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["eval", "reconstruct", "data"])
def test_every_command_has_the_same_error_boundary(tmp_path, capsys, monkeypatch, command):
    """A UserError (a renderer's or a model config's check included) is one line and status 2; a ValueError or
    KeyError that is not one is a bug: its traceback, status 1 (unicorn-train: :func:`expected_error` too)."""
    import importlib

    from unicorn.cli.errors import expected_error
    from unicorn.model.config import ModelConfigError, merge_config
    from unicorn.render import RenderError, build_renderer

    module = importlib.import_module(f"unicorn.cli.{command}")
    args = {
        "eval": ["model.pt", "--device", "cpu", "--out", str(tmp_path / "out")],
        "reconstruct": ["model.pt", "photo.jpg", "--device", "cpu", "--out", str(tmp_path / "out")],
        "data": ["synth", "--out", str(tmp_path / "data"), "--quiet"],
    }[command]
    entry = "_synth" if command == "data" else "run"
    with pytest.raises(RenderError) as render_error:
        build_renderer("layered", image_size=8, sigma=-1.0)
    with pytest.raises(ModelConfigError) as config_error:
        merge_config(pose={"azim_range": (360.0, 0.0)})
    for error in (render_error.value, config_error.value):
        assert isinstance(error, ValueError) and expected_error(error) is error
        monkeypatch.setattr(module, entry, lambda *a, error=error, **k: (_ for _ in ()).throw(error))
        assert module.main(args) == 2
        assert capsys.readouterr().err == f"unicorn-{command}: error: {error}\n"
    for bug in (ValueError("a bug"), KeyError("a bug")):
        assert expected_error(bug) is None
        monkeypatch.setattr(module, entry, lambda *a, bug=bug, **k: (_ for _ in ()).throw(bug))
        with pytest.raises(type(bug)):
            module.main(args)


@pytest.mark.parametrize("text", ["- a list of mine\n", "key: [unclosed\n"], ids=["a-list", "not-yaml"])
def test_synth_refuses_a_folder_with_a_foreign_metadata_yaml(tmp_path, capsys, text):
    from unicorn.cli.data import main

    out = tmp_path / "mine"
    out.mkdir()
    (out / "metadata.yaml").write_text(text)
    before = snapshot(tmp_path)
    assert main(["synth", "--out", str(out), "--models", "10", "--views", "1", "--size", "8", "--quiet"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "metadata.yaml is not a dataset's metadata.yaml" in lines[0], lines
    assert snapshot(tmp_path) == before


SMALL_SYNTH = ["--models", "10", "--views", "1", "--size", "8", "--points", "100", "--quiet"]


def test_synth_into_a_folder_that_holds_the_category_is_refused_and_other_categories_join_it(tmp_path, capsys):
    from unicorn.cli.data import main

    out = tmp_path / "data"
    assert main(["synth", "--out", str(out), "--category", "car", *SMALL_SYNTH]) == 0
    capsys.readouterr()
    before = snapshot(tmp_path)
    assert main(["synth", "--out", str(out), "--category", "car", "--size", "16", *SMALL_SYNTH]) == 2
    assert capsys.readouterr().err == (
        f"unicorn-data: error: {out} already holds car models ({out / '90000003'}): use that dataset as it is, "
        "delete it, or generate into another folder\n"
    )
    assert snapshot(tmp_path) == before
    assert main(["synth", "--out", str(out), "--category", "chair", *SMALL_SYNTH]) == 0  # beside the cars
    metadata = yaml.safe_load((out / "metadata.yaml").read_text())
    assert sorted(metadata) == ["90000001", "90000003"]
    assert {p.name for p in out.iterdir()} == {"90000001", "90000003", "metadata.yaml", "synthetic.json"}
    assert json.loads((out / "synthetic.json").read_text())["categories"] == ["car", "chair"]
    before = snapshot(tmp_path)
    assert main(["synth", "--out", str(out), "--category", "mug", *SMALL_SYNTH, "--seed", "1"]) == 2
    assert capsys.readouterr().err == (  # names --out, not the folder the files are first written to
        f"unicorn-data: error: {out} holds a synthetic dataset generated with --seed 0 (asked: 1); other categories "
        "join it only with the same settings: generate into another folder\n"
    )
    assert snapshot(tmp_path) == before


def test_synth_stopped_part_way_leaves_its_folder_as_it_was(tmp_path, capsys, monkeypatch):
    from unicorn.cli.data import main
    from unicorn.data.synthetic import writer

    out = tmp_path / "data"
    signalled = SignalAtCall(monkeypatch, writer, "_write_model", at=4)  # SIGTERM once three models are written
    assert main(["synth", "--out", str(out), "--category", "car", *SMALL_SYNTH]) == 143
    assert capsys.readouterr().err == "unicorn-data: stopped by SIGTERM\n"
    assert signalled.calls == 4 and list(tmp_path.iterdir()) == []  # no folder, no partial sibling
    # the same command generates the dataset whole
    monkeypatch.setattr(writer, "_write_model", signalled.wrapped)
    assert main(["synth", "--out", str(out), "--category", "car", *SMALL_SYNTH]) == 0
    assert len(list((out / "90000003").glob("car_0_*"))) == 10


def test_a_bogus_device_is_one_line(tmp_path, capsys):
    from unicorn.cli.eval import main

    assert main([str(tmp_path / "model.pt"), "--device", "bogus", "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == (
        "unicorn-eval: error: --device 'bogus' is not a device; use 'auto', 'cpu', 'cuda' or 'cuda:N'\n"
    )
    assert list(tmp_path.iterdir()) == []


def test_an_unquoted_step_file_says_to_quote_it(tmp_path):
    result = unicorn_train(*TINY, "ckpt_path=run/checkpoints/step=0000010.ckpt", "hydra.run.dir=run", cwd=tmp_path)
    lines = error_lines(result.stderr)
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert "mismatched input '='" in lines[0] and "must be quoted for Hydra" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("folder", ["runs/café", "runs/a(1)"])
def test_an_unquoted_folder_hydra_cannot_read_says_to_quote_it(tmp_path, folder):
    result = unicorn_train(*TINY, f"hydra.run.dir={folder}", cwd=tmp_path)
    lines = error_lines(result.stderr)
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert "letters outside ASCII, spaces, brackets or '#' must be quoted for Hydra" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


def test_data_check_takes_the_image_limits_its_message_names(tmp_path, capsys, monkeypatch):
    from PIL import Image

    from unicorn.cli.data import main
    from unicorn.data.images import MAX_IMAGE_BYTES_ENV

    monkeypatch.setenv(MAX_IMAGE_BYTES_ENV, "1073741824")  # restored after the test: the option sets it
    (tmp_path / "imgs").mkdir()
    Image.new("RGB", (40, 40), (200, 10, 10)).save(tmp_path / "imgs" / "a.png")
    args = ["check", "folder", "--root", str(tmp_path / "imgs")]
    assert main([*args, "--max-image-bytes", "1000"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-data: error: ") and "raise the limit with --max-image-bytes" in err
    assert main([*args, "--max-image-bytes", "0"]) == 0  # no limit
    with pytest.raises(SystemExit):
        main([*args, "--max-image-pixels", "-1"])
    assert capsys.readouterr().err.splitlines()[-1] == "unicorn-data check: error: --max-image-pixels must be >= 0"


def test_data_check_all_reads_every_item_and_names_the_unreadable_ones(tmp_path, capsys):
    from PIL import Image

    from unicorn.cli.data import main

    (tmp_path / "imgs").mkdir()
    for name in ("a.png", "b.png"):
        Image.new("RGB", (40, 40), (200, 10, 10)).save(tmp_path / "imgs" / name)
    args = ["check", "folder", "--root", str(tmp_path / "imgs")]
    assert main([*args, "--all"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "read every item: 2 readable, 0 not"
    (tmp_path / "imgs" / "c.png").write_bytes(b"not a picture")  # past the first item, which check shows
    assert main(args) == 0  # the first item only
    capsys.readouterr()
    assert main([*args, "--all"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[-2] == "read every item: 2 readable, 1 not", out
    assert out[-1].startswith(f"  item 2: cannot read image {tmp_path / 'imgs' / 'c.png'}: "), out
    (tmp_path / "imgs" / "0.png").write_bytes(b"not a picture either")  # the first item: --all still reads on
    assert main([*args, "--all"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[1] == "  image: (3, 64, 64) torch.float32", out  # the first readable item's layout
    assert out[-3] == "read every item: 2 readable, 2 not", out
    assert out[-2].startswith(f"  item 0: cannot read image {tmp_path / 'imgs' / '0.png'}: "), out
    assert out[-1].startswith("  item 3: "), out


def test_a_device_this_machine_lacks_is_named(monkeypatch):
    import torch

    from unicorn.cli.errors import UsageError
    from unicorn.cli.options import parse_device

    monkeypatch.setattr(torch.mps, "is_available", lambda: False)
    with pytest.raises(UsageError, match=r"^--device mps: mps is not available on this machine; use 'cpu' or 'auto'$"):
        parse_device("mps")
    assert parse_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("command", ["unicorn-eval", "unicorn-reconstruct", "unicorn-data synth"])
@pytest.mark.parametrize("value", ["", "  "])
def test_an_empty_out_is_a_usage_error(command, value, capsys):
    from unicorn.cli import data, eval, reconstruct

    parsers = {"unicorn-eval": eval, "unicorn-reconstruct": reconstruct, "unicorn-data synth": data}
    head = {"unicorn-eval": ["m.ckpt"], "unicorn-reconstruct": ["m.ckpt", "a.png"], "unicorn-data synth": ["synth"]}
    with pytest.raises(SystemExit) as exit_info:  # an unset variable, --out "$OUT", is not the current folder
        parsers[command].build_parser().parse_args([*head[command], f"--out={value}"])
    assert exit_info.value.code == 2
    assert (
        capsys.readouterr().err.splitlines()[-1]
        == f"{command}: error: argument --out: must name a folder, got {value!r}"
    )


@contextlib.contextmanager
def _train_group(args: list[str], cwd: Path, **env_vars: str):
    """``unicorn-train ARGS`` (one thread, stderr piped, ``env_vars`` added to the environment) in a process group of
    its own, which the DDP processes Lightning starts join; when the block ends, no process of the group may outlive
    the first by 30 s (the rest are killed)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0", **env_vars}
    proc = subprocess.Popen(
        [sys.executable, "-m", "unicorn.cli.train", *args],
        cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        yield proc
        deadline = time.monotonic() + 30
        while _group_alive(proc.pid):
            assert time.monotonic() < deadline, "a DDP process outlived the first one"
            time.sleep(0.2)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def test_a_bad_image_in_one_ddp_process_is_one_line_and_no_process_is_left(tmp_path):
    """Whichever DDP process reads the bad image says so in one line; the other one, which loses its peer, does not
    add a traceback (the first process says that another one ended, or nothing when it was itself the one)."""
    from PIL import Image

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for k in range(15):
        Image.fromarray(rng.integers(0, 255, (40, 40, 3), dtype=np.uint8)).save(photos / f"img{k:02d}.jpg")
    good = (photos / "img00.jpg").read_bytes()
    (photos / "img07b.jpg").write_bytes(good[: len(good) // 3])  # truncated
    args = [*TINY, "dataset=folder", "dataset.categories=null", f"dataset.root={photos}", "dataset.img_size=32",
            "dataset.on_error=raise", "dataset.cache_items=false", "callbacks.heldout=null", "evaluate.enabled=false",
            "trainer=ddp_cpu", "trainer.max_steps=12", f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    with _train_group(args, tmp_path) as proc:
        _, stderr = proc.communicate(timeout=240)
    lines = error_lines(stderr)
    assert proc.returncode == 2, stderr[-3000:]
    assert "Traceback" not in stderr and sum("cannot read image" in line for line in lines) == 1, stderr[-3000:]
    assert all(line.startswith("unicorn-train") for line in lines if "error" in line), lines


def test_a_local_sweep_of_ddp_runs_is_refused_before_anything_starts(tmp_path):
    result = unicorn_train(
        "-m", *TINY, "trainer=ddp_cpu", "seed=1,2", f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path
    )
    lines = error_lines(result.stderr)
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert lines[0].startswith("unicorn-train: error: a sweep (-m) of DDP runs") and "submitit" in lines[0]
    assert not list((tmp_path / "sweep").rglob("*.ckpt"))


def _train_children(pid: int) -> list[int]:
    """The ``unicorn-train`` processes whose parent is ``pid`` (the DDP ranks Lightning starts; not a ``git``
    that the first process runs for its provenance)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                status, command = (entry / "status").read_text(), (entry / "cmdline").read_bytes()
                if f"\nPPid:\t{pid}\n" in status and b"unicorn.cli.train" in command:
                    found.append(int(entry.name))
    return found


# SIGINT only: a SIGTERM to the group can reach the first process twice while Lightning's own SIGTERM handler is
# installed (its notifier forwards the signal), which ends it by the default action; see docs/training.md
@pytest.mark.parametrize("signum", [signal.SIGINT], ids=["SIGINT"])
def test_a_signal_to_every_ddp_process_while_they_start_stops_the_run_in_one_line(tmp_path, signum):
    """A Ctrl-C in the terminal reaches every process of the group while the second DDP process is still starting:
    it does not die of it (Lightning would then SIGKILL the first, leaving a locked, half-made folder); the first
    process stops the run in one line and leaves the folder as it was."""
    run = tmp_path / "run"
    args = [*TINY, "trainer=ddp_cpu", "trainer.max_steps=300", f"hydra.run.dir={run}"]
    with _train_group(args, tmp_path) as proc:
        deadline = time.monotonic() + 120
        while not _train_children(proc.pid):  # the second rank's process is started
            assert proc.poll() is None and time.monotonic() < deadline, "no second process"
            time.sleep(0.05)
        time.sleep(1.0)  # it is importing, or waiting for the first one
        assert not (run / "checkpoints").is_dir() or not any((run / "checkpoints").iterdir())
        os.killpg(proc.pid, signum)
        _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, stderr[-3000:]
    name = signal.Signals(signum).name
    assert f"unicorn-train: stopped by {name} before the first iteration; {run} is left as it was" in stderr
    assert "Traceback" not in stderr and "frame #" not in stderr, stderr[-3000:]
    assert not run.exists()


@pytest.mark.timeout(300)
def test_a_console_that_goes_away_is_not_an_error_of_every_log_record(tmp_path):
    """``unicorn-train ... | head -1``: the console's reader is gone after the first line; the run goes on, its
    records still reach train.log, and stderr does not fill with logging's tracebacks."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.getcwd()}
    args = [sys.executable, "-m", "unicorn.cli.train", *TINY, "trainer.max_steps=2", "hydra.run.dir=run"]
    with subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        proc.stdout.readline()
        proc.stdout.close()  # as head does after its line
        err = proc.stderr.read().decode()
    assert proc.returncode == 0, err
    assert "Logging error" not in err and "BrokenPipeError" not in err, err
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()
    assert len((tmp_path / "run" / "train.log").read_text().splitlines()) > 5  # the records after the first line


def _signal_during_set_up() -> None:
    """unicorn-train's main() with a SIGTERM sent while a job sets up: Hydra has made its folder and rewritten the
    sweep's record, and the task has not yet noted what to put back (the forked command of the test below)."""
    import unicorn.registry as registry
    from unicorn.cli import train

    original = registry.load_plugins

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return original(*args, **kwargs)

    registry.load_plugins = signalled
    train.main()


def test_a_signal_while_a_sweep_sets_up_leaves_its_folder_as_it_was(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "notes.txt").write_text("mine")
    (sweep / "multirun.yaml").write_text("the record of an earlier sweep")
    before = snapshot(sweep)
    result = unicorn_train(
        "-m", *TINY, "seed=1,2", f"hydra.sweep.dir={sweep}", "ckpt_path=last", cwd=tmp_path,
        entry=f"{__name__}:_signal_during_set_up",
    )  # fmt: skip
    assert result.returncode == 143, result.stderr[-3000:]
    assert error_lines(result.stderr)[-1].startswith("unicorn-train: stopped by SIGTERM before the first iteration")
    assert snapshot(sweep) == before
