"""``unicorn-train`` end to end: experiments, overrides, sweeps, DDP, and configs from a non-editable install."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.lit.conftest import TINY, compose_config
from unicorn import __version__
from unicorn.cli.train import config_dir, hydra_argv
from unicorn.config import ConfigError, validate

REPO = Path(__file__).resolve().parents[2]
SHAPENET = "airplane bench cabinet car chair display lamp phone rifle sofa speaker table vessel".split()
REAL = ["cub", "p3d_car", "compcars", "lsun_horse", "lsun_motorbike"]


def unicorn_train(*args: str, cwd: Path, timeout: int = 240) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    return subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_every_experiment_composes_and_validates(tmp_path):
    shipped = sorted(p.stem for p in (config_dir() / "experiment").glob("*.yaml"))
    assert shipped == sorted(
        ["synthetic", "synthetic64", "synthetic_wild", *REAL, *(f"shapenet_{c}" for c in SHAPENET)]
    )
    for name in shipped:
        for model in ("small", "big"):
            cfg = compose_config([f"experiment={name}", f"model={model}", f"paths.output_dir={tmp_path}"])
            typed = validate(cfg)
            assert typed.task_name == name
            assert typed.model.name == model  # the command line wins over the experiment's choice
    shapenet = validate(compose_config(["experiment=shapenet_chair", f"paths.output_dir={tmp_path}"]))
    assert shapenet.model.background is None and shapenet.schedule.texture_averaging.constant_stages == 1
    assert shapenet.schedule.milestones == [49812, 298872, 547932] and shapenet.optim.lr_drop_step == 796992
    wild = validate(compose_config(["experiment=synthetic_wild", f"paths.output_dir={tmp_path}"]))
    default = validate(compose_config(["experiment=synthetic", f"paths.output_dir={tmp_path}"]))
    assert wild.dataset.synthetic.mode == "wild" and wild.model.background is not None
    assert default.dataset.synthetic.mode == "nmr" and default.model.background is None
    # the wild variant trains under the default's budget and schedule (benchmarks/quality.py compares them)
    assert wild.trainer.max_steps == default.trainer.max_steps
    assert wild.schedule.milestones == default.schedule.milestones
    assert default.evaluate.enabled and default.callbacks.heldout is not None
    # the 64 px variant: its own cache folder (the generator's manifest would refuse the 32 px one), same budget
    big = validate(compose_config(["experiment=synthetic64", f"paths.output_dir={tmp_path}"]))
    assert default.dataset.img_size == default.model.image_size == default.dataset.synthetic["image_size"] == 32
    assert big.dataset.img_size == big.model.image_size == big.dataset.synthetic["image_size"] == 64
    assert big.dataset.root != default.dataset.root and big.trainer.max_steps == default.trainer.max_steps
    cub = validate(compose_config(["experiment=cub", "model=big", f"paths.output_dir={tmp_path}"]))
    assert cub.model.stages.texture == [2, 8, 64, 512] and cub.schedule.curriculum.translation == 938
    assert cub.schedule.texture_averaging.random_until_stage == 4 and cub.trainer.max_steps == 3_000_000


def test_experiment_is_a_group_with_a_null_default(tmp_path):
    """lightning-hydra-template's form: `experiment=NAME` (no `+`); no arguments at all run the offline default."""
    assert validate(compose_config(["experiment=cub", f"paths.output_dir={tmp_path}"])).task_name == "cub"
    assert hydra_argv([]) == ["experiment=synthetic"] and hydra_argv(["seed=1"]) == ["seed=1"]
    bare = validate(compose_config([*hydra_argv([]), f"paths.output_dir={tmp_path}"]))
    assert bare.task_name == "synthetic" and bare.model.loss.perceptual == "structural"  # runs offline
    assert bare.trainer.accelerator == "cpu"


def test_help_and_version():
    """--help says what the command does, its main groups and examples, without a config dump; --version."""
    out = subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", "--help"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    assert "train UNICORN" in text and "experiment=NAME" in text
    for group in ("dataset:", "model:", "renderer:", "trainer:", "experiment:"):
        assert group in text
    examples = [line for line in text.splitlines() if line.strip().split(" ")[0] == "unicorn-train"]
    assert len(examples) >= 3
    assert "optim:" not in text and "lr_drop_gamma" not in text and len(text.splitlines()) < 60
    version = subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", "--version"], capture_output=True, text=True, timeout=120
    )
    assert version.returncode == 0 and __version__ in version.stdout


def test_bad_values_are_named(tmp_path):
    base = ["experiment=synthetic", f"paths.output_dir={tmp_path}"]
    with pytest.raises(ConfigError, match=r"optim\.lrr"):
        validate(compose_config([*base, "+optim.lrr=1"]))
    with pytest.raises(ConfigError, match=r"optim\.lr"):
        validate(compose_config([*base, "optim.lr=fast"]))
    with pytest.raises(ConfigError, match=r"schedule\.milestones"):
        validate(compose_config([*base, "schedule.milestones=[5,3,8]"]))
    with pytest.raises(ConfigError, match="find_unused_parameters"):
        validate(compose_config([*base, "trainer.strategy=ddp"]))
    with pytest.raises(ConfigError, match="faces_per_pixl"):
        validate(compose_config([*base, "+renderer.faces_per_pixl=3"]))


def test_bad_override_on_the_command_line(tmp_path):
    typo = unicorn_train("experiment=synthetic", "optim.lrr=1", cwd=tmp_path)
    assert typo.returncode != 0
    assert "lrr" in typo.stdout + typo.stderr and "Traceback" not in typo.stderr
    wrong = unicorn_train("experiment=synthetic", "+optim.lrr=1", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert wrong.returncode == 2
    assert "Key 'lrr' not in 'OptimConfig'" in wrong.stdout + wrong.stderr


def test_end_to_end(synthetic_cache, tmp_path):
    run_dir = tmp_path / "run"
    args = [a for a in TINY if not a.startswith(("logger=", "callbacks.images="))]
    result = unicorn_train(*args, "callbacks.images.every_n_steps=4", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    # Lightning's messages reach the console once (through Hydra's handlers) and train.log
    assert (result.stdout + result.stderr).count("GPU available") == 1
    assert "GPU available" in (run_dir / "train.log").read_text()
    for path in (".hydra/config.yaml", ".hydra/overrides.yaml", "config.yaml", "train.log", "checkpoints/last.ckpt"):
        assert (run_dir / path).is_file(), path
    assert list((run_dir / "tensorboard").glob("events.out.tfevents.*"))
    assert sorted(p.name for p in (run_dir / "images").glob("*.png")) == [
        "step=0000001.png",
        "step=0000004.png",
        "step=0000008.png",
    ]
    columns = next(csv.reader(open(run_dir / "csv" / "metrics.csv")))
    for key in ("train/pose/rgb", "train/pose/uniform", "train/3d/rgb", "train/3d/normal", "pose/share_0", "stage"):
        assert key in columns
    assert "stage 1 -> stage 2" in (run_dir / "train.log").read_text()
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 8 and int(ckpt["state_dict"]["stage"]) == 4


def test_multirun_sweep(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    result = unicorn_train(
        "-m", *TINY, "trainer.max_steps=2", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path, timeout=300
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    for job, seed in (("0", 1), ("1", 2)):
        assert (sweep / job / "checkpoints" / "last.ckpt").is_file()
        assert f"seed: {seed}" in (sweep / job / "config.yaml").read_text()


def test_ddp_two_cpu_processes(synthetic_cache, tmp_path):
    run_dir = tmp_path / "ddp"
    result = unicorn_train(
        *TINY, "trainer=ddp_cpu", "trainer.max_steps=4", f"hydra.run.dir={run_dir}", cwd=tmp_path, timeout=300
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 4
    assert len(ckpt["unicorn"]["ranks"]) == 2  # each rank's neighbour memory and random state


def test_configs_ship_in_the_wheel(tmp_path):
    wheels, target = tmp_path / "wheels", tmp_path / "site"
    pip = [sys.executable, "-m", "pip"]
    subprocess.run([*pip, "wheel", "--no-deps", str(REPO), "-w", str(wheels), "-q"], check=True, timeout=180)
    wheel = next(wheels.glob("unicorn3d-*.whl"))
    subprocess.run([*pip, "install", "--no-deps", "--target", str(target), str(wheel), "-q"], check=True, timeout=180)
    env = {**os.environ, "PYTHONPATH": str(target)}  # the installed copy shadows the editable one
    where = subprocess.run(
        [sys.executable, "-c", "from unicorn.cli.train import config_dir; print(config_dir())"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert Path(where.stdout.strip()) == target / "unicorn" / "conf"
    job = subprocess.run(
        [sys.executable, "-m", "unicorn.cli.train", "--cfg", "job", "experiment=cub"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert job.returncode == 0, job.stderr[-2000:]
    assert "task_name: cub" in job.stdout and "cub_200" in job.stdout
