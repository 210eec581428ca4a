"""``unicorn-train`` end to end: experiments, overrides, sweeps, DDP, and configs from a non-editable install."""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from tests.support.training import TINY, compose_config, error_lines, snapshot, unicorn_train
from unicorn import __version__
from unicorn.cli.train import argument_note, hydra_argv
from unicorn.config import ConfigError, validate
from unicorn.resources import config_dir

REPO = Path(__file__).resolve().parents[2]
SHAPENET = "airplane bench cabinet car chair display lamp phone rifle sofa speaker table vessel".split()
REAL = ["cub", "cub_big", "p3d_car", "compcars", "lsun_horse", "lsun_motorbike"]


EXPERIMENTS = sorted(
    [
        *("synthetic", "synthetic64", "synthetic_9600", "synthetic_long", "synthetic_wild"),
        *REAL,
        *(f"shapenet_{c}" for c in SHAPENET),
    ]
)


def test_the_shipped_experiments():
    assert sorted(p.stem for p in (config_dir() / "experiment").glob("*.yaml")) == EXPERIMENTS


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_composes_and_validates(tmp_path, name):
    for model in ("small", "big"):
        cfg = compose_config([f"experiment={name}", f"model={model}", f"paths.output_dir={tmp_path}"])
        typed = validate(cfg)
        assert typed.task_name == name
        assert typed.model.name == model  # the command line wins over the experiment's choice


def test_the_experiments_set_what_they_say(tmp_path):
    shapenet = validate(compose_config(["experiment=shapenet_chair", f"paths.output_dir={tmp_path}"]))
    assert shapenet.model.background is None and shapenet.schedule.texture_averaging.constant_stages == 1
    assert shapenet.schedule.milestones == [49812, 298872, 547932] and shapenet.optim.lr_drop_step == 796992
    wild = validate(compose_config(["experiment=synthetic_wild", f"paths.output_dir={tmp_path}"]))
    default = validate(compose_config(["experiment=synthetic", f"paths.output_dir={tmp_path}"]))
    assert wild.dataset.synthetic.mode == "wild" and wild.model.background is not None
    assert default.dataset.synthetic.mode == "nmr" and default.model.background is None
    # one recipe: the wild variant is the default with the wild mode, the real family's settings and the scale held
    # through stage 1, nothing else
    by_hand = compose_config(
        [
            "experiment=synthetic",
            "family=real",
            "dataset.synthetic.mode=wild",
            "schedule.curriculum.scale=${schedule.milestones[0]}",
            "task_name=synthetic_wild",
            f"paths.output_dir={tmp_path}",
        ]
    )
    assert OmegaConf.to_yaml(compose_config(["experiment=synthetic_wild", f"paths.output_dir={tmp_path}"])) == (
        OmegaConf.to_yaml(by_hand)
    )
    assert wild.schedule.curriculum.scale == default.schedule.milestones[0]
    assert wild.optim.lr == default.optim.lr and wild.model.shape.n_field_units == default.model.shape.n_field_units
    assert default.evaluate.enabled and default.callbacks.heldout is not None
    # the 64 px variant: its own cache folder (the generator's manifest would refuse the 32 px one), same budget
    big = validate(compose_config(["experiment=synthetic64", f"paths.output_dir={tmp_path}"]))
    assert default.dataset.img_size == default.model.image_size == default.dataset.synthetic["image_size"] == 32
    assert big.dataset.img_size == big.model.image_size == big.dataset.synthetic["image_size"] == 64
    assert big.dataset.root != default.dataset.root and big.trainer.max_steps == default.trainer.max_steps
    cub = validate(compose_config(["experiment=cub", "model=big", f"paths.output_dir={tmp_path}"]))
    assert cub.model.stages.texture == [2, 8, 64, 512] and cub.schedule.curriculum.translation == 938
    assert cub.schedule.texture_averaging.random_until_stage == 4 and cub.trainer.max_steps == 3_000_000
    # the reference's cub_big.yml: the big model, translation and shape freed at 10 and 20 of its epochs, not 5 and 10
    cub_big = validate(compose_config(["experiment=cub_big", f"paths.output_dir={tmp_path}"]))
    assert cub_big.model.stages.texture == [2, 8, 64, 512] and cub_big.model.encoder.shared is False
    assert (cub_big.schedule.curriculum.translation, cub_big.schedule.curriculum.deformation) == (1875, 3750)
    assert cub_big.seed == cub.seed and cub_big.dataset == cub.dataset


def test_experiment_is_a_group_with_a_null_default(tmp_path):
    """A group with a null default: `experiment=NAME` (or `+experiment=NAME`, see test_experiment_forms.py); no
    arguments at all run the offline default."""
    assert validate(compose_config(["experiment=cub", f"paths.output_dir={tmp_path}"])).task_name == "cub"
    assert hydra_argv([]) == ["experiment=synthetic"] and hydra_argv(["seed=1"]) == ["seed=1"]
    bare = validate(compose_config([*hydra_argv([]), f"paths.output_dir={tmp_path}"]))
    assert bare.task_name == "synthetic" and bare.model.loss.perceptual == "structural"  # runs offline
    assert bare.trainer.accelerator == "cpu"


def test_the_first_line_says_which_config_arguments_without_an_experiment_compose():
    assert "offline default +experiment=synthetic" in argument_note([])
    for args in (["seed=1"], ["-m", "seed=1,2"], ["--cfg", "job"]):
        assert "generic config" in argument_note(args), args
    for args in (["+experiment=cub"], ["experiment=cub", "seed=1"], ["-m", "+experiment=a,b"], ["--help"]):
        assert argument_note(args) is None, args


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


def test_training_on_a_generated_set_needs_no_open3d(synthetic_cache, tmp_path):
    """open3d makes the synthetic sets; training on one already made runs without it (a GPU image without open3d)."""
    code = "import sys; sys.modules['open3d'] = None; from unicorn.cli.train import main; sys.exit(main())"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = [sys.executable, "-c", code, *TINY, "trainer.max_steps=2", f"hydra.run.dir={tmp_path / 'run'}"]
    out = subprocess.run(run, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()


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
    logs = ("callbacks.images.every_n_steps=4", "trainer.log_every_n_steps=4")
    result = unicorn_train(*args, *logs, f"hydra.run.dir={run_dir}", cwd=tmp_path, fresh=True)  # a new interpreter
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    # Lightning's messages reach the console once (through Hydra's handlers) and train.log
    assert (result.stdout + result.stderr).count("GPU available") == 1
    assert "GPU available" in (run_dir / "train.log").read_text()
    assert "Tip:" not in result.stdout + result.stderr  # Lightning's advertisements
    # unicorn's warnings: one line each, on the console and in train.log, not Python's file, line and source line
    assert "Warning:" not in result.stderr, result.stderr[-3000:]
    warned = [line for line in (run_dir / "train.log").read_text().splitlines() if "[unicorn.warnings]" in line]
    assert warned and all(line in result.stdout for line in warned)
    assert any("[WARNING] - RenderOverflowWarning: renderer: in the training renders" in line for line in warned)
    for path in (".hydra/config.yaml", ".hydra/overrides.yaml", "config.yaml", "train.log", "checkpoints/last.ckpt"):
        assert (run_dir / path).is_file(), path
    assert list((run_dir / "tensorboard").glob("events.out.tfevents.*"))
    assert sorted(p.name for p in (run_dir / "images").glob("*.png")) == [
        "step=0000001.png",
        "step=0000004.png",
        "step=0000008.png",
    ]
    rows = list(csv.DictReader(open(run_dir / "csv" / "metrics.csv", encoding="utf-8")))
    keys = ("train/pose/rgb", "train/pose/uniform", "train/3d/rgb", "train/3d/normal", "pose/share_0", "stage")
    keys += ("stage/dims_shape", "stage/texture_p", "stage/neighbor")
    assert set(keys) <= set(rows[0])
    # every 4th iteration logs all its values (the stage callback's too), the others none; these iterations are all
    # 3D steps, and each logs the latest pose step's terms as well
    logged = [r for r in rows if r["train/lr"]]
    assert [int(r["step"]) for r in logged] == [3, 7]
    assert all(r[k] for r in logged for k in keys)
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


def test_a_refused_sweep_leaves_the_sweep_folder_as_it_was(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    ran = unicorn_train("-m", *TINY, "trainer.max_steps=1", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr[-3000:]
    record = (sweep / "multirun.yaml").read_bytes()
    before = snapshot(sweep)
    # a new sweep into its folder: refused before anything is written, the earlier sweep's record kept
    again = unicorn_train(
        "-m", *TINY, "trainer.max_steps=2", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path
    )  # fmt: skip
    assert again.returncode == 2
    assert error_lines(again.stderr) == [
        f"unicorn-train: error: {sweep} holds an earlier sweep (multirun.yaml, Hydra's record of it); go on with it "
        "with ckpt_path=last, replace its runs with overwrite=true, or sweep elsewhere (hydra.sweep.dir=...)"
    ]
    assert snapshot(sweep) == before
    # the sweep gone on with other values: every job is refused, and Hydra's record of it is not left behind
    other = unicorn_train(
        "-m", *TINY, "trainer.max_steps=1", "seed=2,1", f"hydra.sweep.dir={sweep}", "ckpt_path=last", cwd=tmp_path
    )  # fmt: skip
    assert other.returncode == 2
    *jobs, summary = error_lines(other.stderr)
    assert len(jobs) == 2 and summary.startswith("unicorn-train: error: every job of the sweep failed (2), each")
    assert "the other jobs ran" not in summary
    assert (sweep / "multirun.yaml").read_bytes() == record
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "1", "multirun.yaml"]
    # one more job than before, going on with the sweep: it runs, and the sweep's record is the new command's
    more = unicorn_train(
        "-m", *TINY, "trainer.max_steps=1", "seed=1,2,3", f"hydra.sweep.dir={sweep}", "ckpt_path=last", cwd=tmp_path
    )  # fmt: skip
    assert more.returncode == 0, more.stderr[-3000:]
    assert (sweep / "2" / "checkpoints" / "last.ckpt").is_file()
    assert "seed=1,2,3" in (sweep / "multirun.yaml").read_text()
    # a sweep refused in a folder of its own: nothing is left of it, nor of the folders Hydra made above it
    new = tmp_path / "new" / "sweep"
    bad = unicorn_train("-m", *TINY, "model.loss.memory_size=-3", "seed=1,2", f"hydra.sweep.dir={new}", cwd=tmp_path)
    assert bad.returncode == 2 and "model.loss.memory_size" in bad.stderr
    assert not (tmp_path / "new").exists()


def test_a_sweep_resumed_with_its_values_in_another_order_is_refused(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    ran = unicorn_train("-m", *TINY, "trainer.max_steps=1", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr[-3000:]
    weights = (sweep / "0" / "checkpoints" / "last.ckpt").read_bytes()
    again = unicorn_train(
        "-m", *TINY, "trainer.max_steps=2", "seed=2,1", f"hydra.sweep.dir={sweep}", "ckpt_path=last", cwd=tmp_path
    )  # fmt: skip
    first, second, summary = error_lines(again.stderr)
    assert again.returncode == 2 and summary.startswith("unicorn-train: error: every job of the sweep failed (2)")
    assert f"job #0 (seed=2): ckpt_path: this job of the sweep would resume {sweep / '0'}" in first
    assert "the run of a job with other values: seed 1 -> 2" in first and "seed 2 -> 1" in second
    assert (sweep / "0" / "checkpoints" / "last.ckpt").read_bytes() == weights
    assert "seed: 1" in (sweep / "0" / "config.yaml").read_text()


def test_a_failing_job_leaves_the_other_jobs_of_a_sweep_to_run(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    ran = unicorn_train("-m", *TINY, "trainer.max_steps=1", "seed=1,-1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    job, summary = error_lines(ran.stderr)
    assert ran.returncode == 2 and job.startswith("unicorn-train: error: job #1 (seed=-1): seed must be")
    assert summary == (
        "unicorn-train: error: 1 job(s) of the sweep failed, each said above: #1 (seed=-1); the other jobs ran (the "
        f"same command with hydra.sweep.dir={sweep} ckpt_path=last goes on with the sweep once the failures are fixed)"
    )
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "2", "multirun.yaml"]  # job 1 left nothing
    assert all((sweep / job / "checkpoints" / "last.ckpt").is_file() for job in ("0", "2"))


def test_a_bug_in_jobs_of_a_sweep_is_said_for_each_job_and_the_summary_kept(synthetic_cache, tmp_path):
    """Hydra raises only the first failed job's error once the sweep ran: each bug is said as its job fails, with
    its traceback, and the line naming the failed jobs is not lost."""
    sweep = tmp_path / "sweep"
    bug = "+callbacks.extra.bug={_target_: tests.lit.faults.Raise, step: 1}"
    ran = unicorn_train(
        "-m", *TINY, "trainer.max_steps=2", bug, "seed=-1,0,1", f"hydra.sweep.dir={sweep}", cwd=REPO, timeout=300
    )
    lines = error_lines(ran.stderr)
    assert ran.returncode == 1, ran.stderr[-3000:]
    assert lines[0].startswith("unicorn-train: error: job #0 (seed=-1): seed must be")
    for job in ("#1 (seed=0)", "#2 (seed=1)"):
        assert f"unicorn-train: error: job {job}: a bug, its traceback:" in lines
    assert ran.stderr.count("ZeroDivisionError: a bug injected at iteration 1") == 2
    assert lines[-1] == (
        "unicorn-train: error: every job of the sweep failed (3), each said above: #0 (seed=-1), #1 (seed=0), #2 "
        f"(seed=1) (the same command with hydra.sweep.dir={sweep} ckpt_path=last goes on with the sweep once the "
        "failures are fixed)"
    )
    assert sorted(p.name for p in sweep.iterdir()) == ["1", "2", "multirun.yaml"]  # the bugs came after iteration 0


def test_a_job_refused_in_the_folder_of_an_earlier_job_of_its_sweep_leaves_that_run(synthetic_cache, tmp_path):
    """Two jobs whose folders are named alike (``hydra.sweep.subdir`` naming a value the jobs share): the second is
    refused, and the first one's run, which the sweep made after it started, is not taken for the second's and
    removed."""
    sweep = tmp_path / "sweep"
    ran = unicorn_train(
        "-m", *TINY, "trainer.max_steps=1", "seed=1,2", f"hydra.sweep.dir={sweep}",
        "hydra.sweep.subdir=${hydra.job.name}", cwd=tmp_path,
    )  # fmt: skip
    job, _ = error_lines(ran.stderr)
    assert ran.returncode == 2 and f"job #1 (seed=2): {sweep / 'train'} already holds a run" in job, ran.stderr[-3000:]
    assert (sweep / "train" / "checkpoints" / "last.ckpt").is_file()
    assert "seed: 1" in (sweep / "train" / "config.yaml").read_text()


def test_a_sweep_whose_jobs_share_one_folder_is_refused_before_anything_is_written(tmp_path):
    """``hydra.sweep.subdir=.`` (the sweep's folder, which holds the sweep's record and lock) or one name without a
    value of the job for several jobs: refused in one line naming the setting, and no folder is made; one job in a
    folder of a fixed name runs."""
    sweep = tmp_path / "sweep"
    itself = unicorn_train("-m", *TINY, "seed=1,2", f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=.", cwd=tmp_path)
    assert itself.returncode == 2
    assert error_lines(itself.stderr) == [
        f"unicorn-train: error: hydra.sweep.subdir=.: the jobs would train in the sweep's folder {sweep} itself, which "
        "holds the sweep's record; give each job a folder of its own (hydra.sweep.subdir=${hydra.job.num}, the "
        f"default), or train one run without -m (hydra.run.dir={sweep})"
    ]
    one = unicorn_train("-m", *TINY, "seed=1", f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=.", cwd=tmp_path)
    assert one.returncode == 2 and "hydra.sweep.subdir=.: the jobs would train in the sweep's folder" in one.stderr
    shared = unicorn_train(
        "-m", *TINY, "seed=1,2,3", "overwrite=true,false", f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=same",
        cwd=tmp_path,
    )  # fmt: skip
    assert shared.returncode == 2
    assert error_lines(shared.stderr) == [
        f"unicorn-train: error: hydra.sweep.subdir=same: the 6 jobs of the sweep would all train in one folder, "
        f"{sweep / 'same'}, which holds one run; give each job a folder of its own (hydra.sweep.subdir="
        "${hydra.job.num}, the default)"
    ]
    assert not sweep.exists()


def test_a_single_job_sweep_runs_in_a_folder_of_a_fixed_name(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    ran = unicorn_train(
        "-m", *TINY, "trainer.max_steps=1", "seed=3", f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=only",
        cwd=tmp_path,
    )  # fmt: skip
    assert ran.returncode == 0, ran.stderr[-3000:]
    assert "seed: 3" in (sweep / "only" / "config.yaml").read_text()


def test_a_sweep_that_kept_nothing_is_not_told_to_resume(tmp_path):
    sweep = tmp_path / "new" / "sweep"
    bad = unicorn_train("-m", *TINY, "model.loss.memory_size=-3", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert bad.returncode == 2 and not (tmp_path / "new").exists()
    assert error_lines(bad.stderr)[-1] == (
        "unicorn-train: error: every job of the sweep failed (2), each said above: #0 (seed=1), #1 (seed=2) (nothing "
        "of the sweep was kept: the same command runs it again once the failures are fixed)"
    )


def _signal_in_the_second_jobs_build() -> None:
    """unicorn-train's main() that gets SIGTERM once the second job of a sweep is built, before its first
    iteration (the forked command of the test below)."""
    from unicorn.cli import train
    from unicorn.lit import run as lit_run

    build, built = lit_run.build, []

    def signalled(cfg):
        built.append(build(cfg))
        if len(built) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return built[-1]

    lit_run.build = signalled
    train.main()


def test_a_sweep_stopped_before_a_later_jobs_first_iteration_says_how_it_goes_on(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    args = ["-m", *TINY, "trainer.max_steps=1", "seed=1,2,3", f"hydra.sweep.dir={sweep}"]
    stopped = unicorn_train(*args, cwd=tmp_path, entry=f"{__name__}:_signal_in_the_second_jobs_build")
    assert stopped.returncode == 143, stopped.stderr[-3000:]
    assert error_lines(stopped.stderr)[-1] == (
        f"unicorn-train: stopped by SIGTERM before the first iteration; {sweep / '1'} is left as it was; the sweep "
        f"goes on with the same command and hydra.sweep.dir={sweep} ckpt_path=last"
    )
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "multirun.yaml"]
    went_on = unicorn_train(*args, "ckpt_path=last", cwd=tmp_path)  # as it says
    assert went_on.returncode == 0, went_on.stderr[-3000:]
    assert all((sweep / job / "checkpoints" / "last.ckpt").is_file() for job in ("0", "1", "2"))


def test_the_evaluation_after_training_names_the_report_only_when_it_writes_one(synthetic_cache, tmp_path, caplog):
    import logging

    from tests.support.training import build_run
    from unicorn.lit.run import fit

    evaluate = ["evaluate.enabled=true", "evaluate.max_images=1", "evaluate.shape_points=0", "trainer.max_steps=1"]
    with caplog.at_level(logging.INFO, logger="unicorn.train"):
        fit(build_run(tmp_path, *evaluate, "evaluate.report_samples=0", "evaluate.num_points=100"))
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("evaluation")]
    assert not (tmp_path / "eval" / "report.html").exists()
    assert said == [f"evaluation metrics: {tmp_path / 'eval' / 'metrics.csv'} (no report: evaluate.report_samples=0)"]


def test_ddp_two_cpu_processes(synthetic_cache, tmp_path):
    run_dir = tmp_path / "ddp"
    result = unicorn_train(
        *TINY,
        "trainer=ddp_cpu",
        "trainer.max_steps=4",
        f"hydra.run.dir={run_dir}",
        cwd=tmp_path,
        timeout=300,
        fresh=True,  # Lightning starts the second process by running this command line again
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
        [sys.executable, "-c", "from unicorn.resources import config_dir; print(config_dir())"],
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


def test_user_errors_are_one_line_and_leave_no_run_folder(synthetic_cache, tmp_path):
    run_dir = tmp_path / "run"
    cases = [
        (["dataset.batch_size=0"], "dataset.batch_size must be >= 1, got 0"),
        ([f"ckpt_path={tmp_path / 'missing.ckpt'}"], "ckpt_path: no checkpoint file at"),
        (["optim.lrr=1"], "lrr"),  # Hydra's own composition error, put on one line
    ]
    for overrides, message in cases:
        result = unicorn_train(*TINY, *overrides, f"hydra.run.dir={run_dir}", cwd=tmp_path)
        lines = error_lines(result.stderr)
        assert result.returncode == 2, result.stderr[-2000:]
        assert len(lines) == 1 and lines[0].startswith("unicorn-train: error: ") and message in lines[0], lines
        assert not run_dir.exists(), overrides
    # --debug (or HYDRA_FULL_ERROR=1) shows where it came from
    debug = unicorn_train("--debug", *TINY, "dataset.batch_size=0", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert debug.returncode != 0 and "Traceback" in debug.stderr and "ConfigError" in debug.stderr


def test_missing_dataset_is_one_line(tmp_path):
    run_dir = tmp_path / "run"
    result = unicorn_train(
        "experiment=cub", "model=tiny", "logger=default", f"dataset.root={tmp_path / 'nothing'}",
        f"hydra.run.dir={run_dir}", cwd=tmp_path,
    )  # fmt: skip
    lines = error_lines(result.stderr)
    assert result.returncode == 2 and len(lines) == 1 and "nothing" in lines[0], result.stderr[-3000:]
    assert not run_dir.exists()  # not even the loggers' folders


def test_a_missing_dataset_is_said_before_the_missing_vgg16_weights(tmp_path):
    result = unicorn_train(
        "+experiment=cub", f"dataset.root={tmp_path / 'birds'}", f"paths.vgg16={tmp_path / 'vgg16.pth'}",
        f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
    )  # fmt: skip
    (line,) = error_lines(result.stderr)
    assert result.returncode == 2 and "CUB-200-2011 root not found" in line and "birds" in line, line


def test_a_run_folder_is_reused_only_to_resume_or_overwrite(synthetic_cache, tmp_path):
    from tests.support.training import build_run
    from unicorn.io.run_folder import RunFolderError
    from unicorn.lit.run import fit

    fit(build_run(tmp_path, "trainer.max_steps=2"))
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()
    with pytest.raises(RunFolderError, match=r"already holds a run \(checkpoints/last\.ckpt\).*ckpt_path=last"):
        build_run(tmp_path)
    assert build_run(tmp_path, "ckpt_path=last").ckpt_path == str(tmp_path / "checkpoints" / "last.ckpt")
    (tmp_path / "notes.txt").write_text("mine")
    fresh = build_run(tmp_path, "overwrite=true", "trainer.max_steps=1")
    assert fresh.ckpt_path is None and not (tmp_path / "checkpoints").exists()
    [aside] = tmp_path.glob(f".overwritten-{os.getpid()}-*")  # until the new run's first iteration
    assert (aside / "checkpoints" / "last.ckpt").is_file()
    fit(fresh)
    assert not aside.exists() and torch.load(tmp_path / "checkpoints" / "last.ckpt")["global_step"] == 1
    assert (tmp_path / "notes.txt").read_text() == "mine"  # only the run's own outputs are deleted


def test_a_resume_names_the_settings_it_changes_and_refuses_those_its_checkpoint_fixes(
    synthetic_cache, tmp_path, caplog
):
    """A resumed run takes Adam's and the schedule's settings from its checkpoint: changing them is refused (it was
    silently ignored, while config.yaml recorded the new values); other changes are listed."""
    import logging

    from tests.support.training import build_run
    from unicorn.config import ConfigError
    from unicorn.io.serialization import CheckpointError
    from unicorn.lit.run import fit

    fit(build_run(tmp_path, "trainer.max_steps=2"))
    config = (tmp_path / "config.yaml").read_bytes()
    for override, said in [
        ("optim.lr=1e-3", r"optim\.lr 0\.0002 -> 0\.001"),
        ("optim.adam_state=shared", r"optim\.adam_state 'per_step' -> 'shared'"),
        ("optim.lr_drop_step=1", r"optim\.lr_drop_step 6 -> 1"),
    ]:
        with pytest.raises(ConfigError, match=rf"keeps its checkpoint's optimiser and schedule.*{said}; resume with"):
            build_run(tmp_path, "ckpt_path=last", override)
        assert (tmp_path / "config.yaml").read_bytes() == config  # refused before anything is written
    # the data too: a run resumed on other data would record it as the run's, and be evaluated on it
    for override, said in [
        ("dataset.categories=car", r"dataset\.categories 'chair' -> 'car'"),
        ("dataset.synthetic.n_models=6", r"dataset\.synthetic\.n_models 5 -> 6"),
    ]:
        with pytest.raises(ConfigError, match=rf"trains on its run's data.*{said}; resume with the run's data"):
            build_run(tmp_path, "ckpt_path=last", override)
        assert (tmp_path / "config.yaml").read_bytes() == config
    with caplog.at_level(logging.WARNING, logger="unicorn.train"):
        build_run(tmp_path, "ckpt_path=last", "trainer.max_steps=3", "dataset.batch_size=2")
    changed = [r.getMessage() for r in caplog.records if "resuming with settings other than" in r.getMessage()]
    assert len(changed) == 1 and changed[0].endswith(": dataset.batch_size 4 -> 2"), changed
    (tmp_path / "config.yaml").unlink()  # a checkpoint without its run's record: the optimisers are counted
    with pytest.raises(CheckpointError, match=r"holds 2 optimiser state\(s\) and this run has 1"):
        fit(build_run(tmp_path, "ckpt_path=last", "trainer.max_steps=3", "optim.adam_state=shared"))


def test_a_moved_run_folder_resumes_without_listing_its_paths(synthetic_cache, tmp_path, caplog):
    import logging
    import shutil

    from tests.support.training import build_run
    from unicorn.lit.run import fit

    fit(build_run(tmp_path / "here", "trainer.max_steps=2", "logger=default"))  # TensorBoard and CSV: save_dir
    shutil.copytree(tmp_path / "here", tmp_path / "moved")
    with caplog.at_level(logging.WARNING, logger="unicorn.train"):
        build_run(tmp_path / "moved", "ckpt_path=last", "trainer.max_steps=3", "logger=default")
        build_run(tmp_path / "moved", "ckpt_path=last", "trainer.max_steps=3", "logger=default", "dataset.batch_size=2")
    changed = [r.getMessage() for r in caplog.records if "resuming with settings other than" in r.getMessage()]
    assert len(changed) == 1 and changed[0].endswith(": dataset.batch_size 4 -> 2"), changed  # not the loggers'


def test_progress_bar_can_be_disabled(synthetic_cache, tmp_path):
    from tests.support.training import build_run
    from unicorn.lit.run import fit

    run = build_run(tmp_path, "trainer.enable_progress_bar=false", "trainer.max_steps=1")
    fit(run)
    assert run.trainer.global_step == 1 and run.trainer.progress_bar_callback is None


def test_values_are_range_checked_where_declared(tmp_path):
    base = ["experiment=synthetic", f"paths.output_dir={tmp_path}"]
    for override, message in [
        ("dataset.batch_size=0", r"dataset\.batch_size must be >= 1, got 0"),
        ("dataset.num_workers=-1", r"dataset\.num_workers must be >= 0"),
        ("model.pose.n_azim=0", r"model\.pose\.n_azim must be >= 1"),
        ("model.loss.min_angle=270", r"model\.loss\.min_angle must be in \[0, 180\]"),
        ("callbacks.checkpoint.keep=-2", r"callbacks\.checkpoint\.keep must be >= -1"),
        ("renderer.faces_per_pixel=0", r"renderer\.faces_per_pixel must be a whole number >= 1"),
        ("renderer.sigma=nan", r"renderer\.sigma must be a finite number >= 0"),
        ("optim.lr=inf", r"optim\.lr must be a finite number > 0, got inf"),
        ("optim.betas=[2,3]", r"optim\.betas must lie in \[0, 1\), got \[2\.0, 3\.0\]"),
        ("optim.betas=[0.9,1.0]", r"optim\.betas must lie in \[0, 1\)"),
        ("optim.eps=inf", r"optim\.eps must be a finite number >= 0, got inf"),
        ("model.template.scale=nan", r"model\.template\.scale must be a finite number"),
        ("dataset.on_error=maybe", r"dataset\.on_error must be one of \('skip', 'raise'\), got 'maybe'"),
        ("init_from=m.pt", None),  # with ckpt_path below
    ]:
        if message is None:
            with pytest.raises(ConfigError, match="init_from and ckpt_path exclude each other"):
                validate(compose_config([*base, override, "ckpt_path=run/checkpoints/last.ckpt"]))
            validate(compose_config([*base, override, "ckpt_path=last"]))  # init_from starts it, a requeue resumes
            continue
        with pytest.raises(ConfigError, match=message):
            validate(compose_config([*base, override]))


def test_dataset_without_its_root_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"dataset\.root is required by dataset 'folder'"):
        validate(compose_config(["dataset=folder", f"paths.output_dir={tmp_path}"]))


def test_expected_failures_inside_training_are_one_line_and_leave_no_run_folder(synthetic_cache, tmp_path):
    from tests.support.evaluation import tiny_checkpoint

    run_dir = tmp_path / "run"
    saved = tiny_checkpoint(tmp_path / "saved.pt")
    cases = [
        # found by Lightning when it loads the file, after the loggers made csv/ (and tensorboard/)
        ([f"ckpt_path={saved}", "logger=csv"], rf"ckpt_path: {saved} is a unicorn.io.save_model file.*init_from="),
        ([f"ckpt_path={tmp_path}"], "is a directory, not a checkpoint file"),
    ]
    if not torch.cuda.is_available():
        cases.append((["trainer.accelerator=gpu"], r"trainer \(accelerator=gpu.*\): No supported gpu backend"))
    for overrides, message in cases:
        result = unicorn_train(*TINY, *overrides, f"hydra.run.dir={run_dir}", cwd=tmp_path)
        lines = error_lines(result.stderr)
        assert result.returncode == 2, result.stderr[-3000:]
        assert len(lines) == 1 and lines[0].startswith("unicorn-train: error: "), lines
        assert re.search(message, lines[0]), lines
        assert not run_dir.exists(), overrides


def test_a_bug_keeps_its_traceback_and_the_folder_stays_usable(synthetic_cache, tmp_path):
    run_dir = tmp_path / "run"
    bug = "+callbacks.extra.bug={_target_: tests.lit.faults.Raise, step: 0}"
    result = unicorn_train(*TINY, "logger=csv", bug, f"hydra.run.dir={run_dir}", cwd=REPO)
    assert result.returncode == 1 and "Traceback" in result.stderr, result.stderr[-3000:]
    assert "ZeroDivisionError: a bug injected at iteration 0" in result.stderr
    assert not run_dir.exists()  # failed before its first iteration: nothing blocks the same command
    again = unicorn_train(*TINY, "trainer.max_steps=1", f"hydra.run.dir={run_dir}", cwd=REPO)
    assert again.returncode == 0, again.stderr[-3000:]
    # after an iteration the folder stays, and its train.log ends with the traceback
    later = tmp_path / "later"
    bug = "+callbacks.extra.bug={_target_: tests.lit.faults.Raise, step: 2}"
    result = unicorn_train(*TINY, bug, f"hydra.run.dir={later}", cwd=REPO)
    assert result.returncode == 1 and "Traceback" in result.stderr, result.stderr[-3000:]
    logged = (later / "train.log").read_text()
    tail = logged[logged.index("[unicorn.train][ERROR] - failed: ZeroDivisionError") :]
    assert "Traceback" in tail and tail.rstrip().endswith("ZeroDivisionError: a bug injected at iteration 2")


def test_a_refused_run_touches_nothing_in_the_folder(synthetic_cache, tmp_path):
    run_dir = tmp_path / "run"
    first = unicorn_train(*TINY, "trainer.max_steps=1", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    assert (run_dir / ".hydra" / "config.yaml").is_file() and (run_dir / ".hydra" / "overrides.yaml").is_file()
    assert "output_subdir: .hydra" in (run_dir / ".hydra" / "hydra.yaml").read_text()
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in run_dir.rglob("*") if p.is_file()}
    second = unicorn_train(*TINY, "trainer.max_steps=2", "seed=5", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert second.returncode == 2 and "already holds a run" in second.stderr, second.stderr[-3000:]
    after = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in run_dir.rglob("*") if p.is_file()}
    assert after == before


def test_a_divergence_a_callback_renders_first_is_one_line_and_keeps_the_run(synthetic_cache, tmp_path):
    """The update of iteration 0 at this rate blows the weights up; the picture of iteration 1 (rendered at the end of
    that iteration, before the next step's own check) meets them first: one line, status 2, the run's folder kept."""
    run_dir = tmp_path / "run"
    args = [a for a in TINY if not a.startswith("callbacks.images=")]
    result = unicorn_train(
        *args, "callbacks.images.every_n_steps=1", "optim.lr=1e30", f"hydra.run.dir={run_dir}", cwd=tmp_path
    )
    assert result.returncode == 2, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    assert error_lines(result.stderr)[-1:] == [
        "unicorn-train: error: the training diverged: the weights after iteration 0 give non-finite values (verts "
        "contains NaN or infinite values); train again, or resume from an earlier checkpoint, with a lower optim.lr"
    ]
    assert "the training diverged" in (run_dir / "train.log").read_text()  # the iteration ran: its folder stays


def test_a_plugin_that_cannot_be_imported_leaves_the_folders_as_they_were(tmp_path, monkeypatch):
    monkeypatch.setenv("UNICORN_PLUGINS", "probe_no_such_plugin")
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "notes.txt").write_text("mine")
    for run_dir in (tmp_path / "new", existing):
        result = unicorn_train(*TINY, f"hydra.run.dir={run_dir}", cwd=tmp_path)
        assert result.returncode == 2, result.stderr[-3000:]
        assert result.stderr.strip().splitlines()[-1] == (
            "unicorn-train: error: UNICORN_PLUGINS: cannot import 'probe_no_such_plugin': ModuleNotFoundError: No "
            "module named 'probe_no_such_plugin'"
        )
    assert not (tmp_path / "new").exists()  # not even Hydra's train.log
    assert sorted(p.name for p in existing.iterdir()) == ["notes.txt"]


def test_a_read_only_run_folder_is_one_line(tmp_path):
    # a PermissionError as a read-only disk gives, raised by Hydra while it creates the folder (before the task)
    from unicorn.cli.hydra_app import hydra_failure as _hydra_failure

    report = (
        'Error executing job with overrides: []\nTraceback (most recent call last):\n  File "x.py", line 1\n'
        "OSError: [Errno 30] Read-only file system: '/ro/run'\n\nSet the environment variable HYDRA_FULL_ERROR=1 "
        "for a complete stack trace.\n"
    )
    assert _hydra_failure(report) == "[Errno 30] Read-only file system: '/ro/run'"
    assert _hydra_failure(report.replace("OSError", "ZeroDivisionError")) is None  # a bug: the traceback stays
    # an existing folder on a read-only disk: logging cannot open the run's log
    chained = report.replace(
        "'/ro/run'\n",
        "'/ro/run/train.log'\n\nThe above exception was the direct cause of the following exception:\n\n"
        'Traceback (most recent call last):\n  File "y.py", line 2\n'
        "ValueError: Unable to configure handler 'file'\n",
    )
    assert (
        _hydra_failure(chained) == "cannot write the run's log: [Errno 30] Read-only file system: '/ro/run/train.log'"
    )
    assert _hydra_failure(chained.replace("OSError", "KeyError")) is None
    assert _hydra_failure("Could not override 'optim.lrr'.\nKey 'lrr' is not in struct") == (
        "Could not override 'optim.lrr'. Key 'lrr' is not in struct"
    )
    # argparse's usage lines are left out; a launcher that is not installed is named as a plugin to install
    usage = "usage: unicorn-train [--help] [overrides ...]\nunicorn-train: error: unrecognized arguments: seed=1\n"
    assert _hydra_failure(usage) == (
        "unrecognized arguments: seed=1 (the key=value overrides go together, after Hydra's options: --cfg job seed=1)"
    )
    missing = "In 'hydra/config': Could not find 'hydra/launcher/submitit_slurm'\n\nAvailable options: basic"
    assert _hydra_failure(missing).endswith("pip install hydra-submitit-launcher)")
