"""``unicorn-train +experiment=NAME`` and ``experiment=NAME`` compose the same run: single runs, sweeps, ``--cfg job``,
``--help`` and ``-cd`` (a config directory of the user's)."""

from __future__ import annotations

import json
import shlex
import subprocess
from pathlib import Path

import pytest
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from tests.support.training import TINY, compose_config, unicorn_train
from unicorn.cli import train
from unicorn.cli.train import experiment_overrides, hydra_argv
from unicorn.config import model_config, validate

#: a user's preset in a config directory of their own (``-cd my_conf``): it overrides a group and values
MINE = """# @package _global_
defaults:
  - override /dataset: synthetic
  - override /model: tiny
  - _self_
task_name: mine
seed: 7
optim:
  lr: 3.0e-4
"""


def _write_composed(cfg) -> None:
    """The task of :func:`_compose_only`: the job's composed config (unresolved, so that the two forms can be
    compared) and Hydra's choice of experiment, written into the job's folder."""
    hydra = HydraConfig.get()
    out = Path(hydra.runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "composed.yaml").write_text(OmegaConf.to_yaml(cfg))
    (out / "choice.json").write_text(json.dumps(hydra.runtime.choices.get("experiment")))


def _compose_only() -> None:
    """unicorn-train's main() with its task (build and train) replaced by :func:`_write_composed` (the forked
    command of :func:`compose_only`: the replacement stays in that process)."""
    train._task = _write_composed
    train.main()


def compose_only(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return unicorn_train(*args, cwd=cwd, timeout=120, entry=f"{__name__}:_compose_only")


def test_only_the_appending_experiment_form_is_rewritten():
    argv = ["-m", "--cfg", "job", "-cd", "my_conf", "+experiment=a,b", "experiment=c", "+experiment.x=1", "+seed=2"]
    assert experiment_overrides(argv) == [
        "-m",
        "--cfg",
        "job",
        "-cd",
        "my_conf",
        "experiment=a,b",
        "experiment=c",
        "+experiment.x=1",
        "+seed=2",
    ]
    assert hydra_argv(["+experiment=cub"]) == ["experiment=cub"] and hydra_argv([]) == ["experiment=synthetic"]
    # Hydra's add-or-override form, which it refuses for a config group ("force-add of config groups")
    assert experiment_overrides(["++experiment=cub", "++experiment.x=1"]) == ["experiment=cub", "++experiment.x=1"]


def test_both_forms_compose_the_same_config_with_the_experiment_applied_last(tmp_path):
    out = f"paths.output_dir={tmp_path}"
    for name in ("synthetic", "cub", "shapenet_chair"):
        for extra in ([], ["model=big"]):
            plus = compose_config(experiment_overrides([f"+experiment={name}", *extra, out]))
            plain = compose_config([f"experiment={name}", *extra, out])
            assert OmegaConf.to_yaml(plus) == OmegaConf.to_yaml(plain)
            typed = validate(plus)
            assert typed.task_name == name  # the experiment overrides train.yaml's `task_name: train`
            assert typed.model.name == ("big" if extra else validate(plain).model.name)  # the command line wins
    synthetic = validate(compose_config(experiment_overrides(["+experiment=synthetic", out])))
    assert synthetic.evaluate.enabled and synthetic.trainer.accelerator == "cpu"  # train.yaml says false, default


def test_cfg_job_prints_the_same_config_for_both_forms(tmp_path):
    plus = unicorn_train("--cfg", "job", "+experiment=cub", "model=big", cwd=tmp_path)
    plain = unicorn_train("--cfg", "job", "experiment=cub", "model=big", cwd=tmp_path)
    assert plus.returncode == 0 and plain.returncode == 0, plus.stderr[-2000:] + plain.stderr[-2000:]
    assert plus.stdout == plain.stdout and "task_name: cub" in plus.stdout


def test_help_with_either_form(tmp_path):
    for form in ("+experiment=cub", "experiment=cub"):
        result = unicorn_train("--help", form, cwd=tmp_path)
        assert result.returncode == 0, result.stderr[-2000:]
        assert "unicorn-train +experiment=cub" in result.stdout and "experiment:" in result.stdout


def test_a_user_config_dir_with_its_own_experiment(tmp_path):
    (tmp_path / "my_conf" / "experiment").mkdir(parents=True)
    (tmp_path / "my_conf" / "experiment" / "mine.yaml").write_text(MINE)
    plus = unicorn_train("--cfg", "job", "-cd", "my_conf", "+experiment=mine", cwd=tmp_path)
    plain = unicorn_train("--cfg", "job", "--config-dir=my_conf", "experiment=mine", cwd=tmp_path)
    assert plus.returncode == 0 and plain.returncode == 0, plus.stderr[-2000:] + plain.stderr[-2000:]
    assert plus.stdout == plain.stdout
    composed = OmegaConf.create(plus.stdout)
    assert composed.task_name == "mine" and composed.seed == 7 and composed.optim.lr == 3.0e-4
    # the shipped presets stay reachable next to the user's
    shipped = unicorn_train("--cfg", "job", "-cd", "my_conf", "+experiment=cub", cwd=tmp_path)
    assert shipped.returncode == 0 and "task_name: cub" in shipped.stdout


def test_sweeps_and_single_runs_compose_the_same_jobs_with_both_forms(tmp_path):
    """A sweep over seeds and one over experiments, each job composed (building and training are replaced)."""
    composed = {}
    for form in ("+experiment", "experiment"):
        sweep = tmp_path / form
        result = compose_only("-m", f"{form}=synthetic", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
        assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
        jobs = [(sweep / job / "composed.yaml").read_text() for job in ("0", "1")]
        assert [OmegaConf.create(j).seed for j in jobs] == [1, 2]
        assert all(OmegaConf.create(j).task_name == "synthetic" for j in jobs)
        assert all(json.loads((sweep / job / "choice.json").read_text()) == "synthetic" for job in ("0", "1"))
        composed[form] = jobs
    assert composed["+experiment"] == composed["experiment"]

    sweep = tmp_path / "experiments"
    result = compose_only("-m", "+experiment=synthetic,cub", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    names = [OmegaConf.create((sweep / job / "composed.yaml").read_text()).task_name for job in ("0", "1")]
    assert names == ["synthetic", "cub"]

    single = {}
    for form in ("+experiment", "experiment"):
        run = tmp_path / f"run{form}"
        result = compose_only(f"{form}=cub", f"hydra.run.dir={run}", cwd=tmp_path)
        assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
        single[form] = (run / "composed.yaml").read_text()
    assert single["+experiment"] == single["experiment"] and "task_name: cub" in single["experiment"]


def test_keys_of_a_preset_that_names_only_some_of_a_group_are_overridden_without_a_plus(tmp_path):
    args = ["experiment=synthetic", "callbacks.heldout.split=test", "callbacks.heldout.shape_points=0",
            "callbacks.extra.timer={_target_:lightning.pytorch.callbacks.Timer}", "dataset.synthetic.n_views=6",
            "seed=3", "+callbacks.heldout.at_start=false", "-m", "callbacks.heldout.every_n_steps=10,20"]  # fmt: skip
    rewritten = train.open_node_overrides(args)
    assert rewritten == [
        "experiment=synthetic", "++callbacks.heldout.split=test", "++callbacks.heldout.shape_points=0",
        "++callbacks.extra.timer={_target_:lightning.pytorch.callbacks.Timer}", "++dataset.synthetic.n_views=6",
        "seed=3", "+callbacks.heldout.at_start=false", "-m", "++callbacks.heldout.every_n_steps=10,20",
    ]  # fmt: skip
    # the synthetic preset names some of callbacks.heldout's keys: Hydra refuses the others without a +
    typed = validate(compose_config([*rewritten[:6], f"paths.output_dir={tmp_path}"]))
    assert typed.callbacks.heldout.split == "test" and typed.callbacks.heldout.shape_points == 0
    assert typed.callbacks.heldout.every_n_steps == 600 and typed.dataset.synthetic.n_views == 6
    assert typed.callbacks.extra.timer._target_ == "lightning.pytorch.callbacks.Timer"
    # a preset without held-out scoring: naming one key turns it on with the others' defaults
    typed = validate(
        compose_config(
            train.open_node_overrides(
                ["experiment=shapenet_car", "callbacks.heldout.every_n_steps=7", f"paths.output_dir={tmp_path}"]
            )
        )
    )
    assert typed.callbacks.heldout.every_n_steps == 7 and typed.callbacks.heldout.split == "val"
    # the whole group as a mapping, as the docs write it, merges into the preset's
    given = train.open_node_overrides(["experiment=synthetic", "callbacks.heldout={every_n_steps:10,split:test}"])
    typed = validate(compose_config([*given, f"paths.output_dir={tmp_path}"]))
    assert typed.callbacks.heldout.split == "test" and typed.callbacks.heldout.max_images == 16  # the preset's
    # a misspelt key is not rewritten: Hydra names it; nor is a config group's choice, nor a node turned off
    assert train.open_node_overrides(["callbacks.heldout.bogus=1"]) == ["callbacks.heldout.bogus=1"]
    assert train.open_node_overrides(["renderer=hard", "logger=none"]) == ["renderer=hard", "logger=none"]
    off = validate(
        compose_config(
            [
                *train.open_node_overrides(["experiment=synthetic", "callbacks.heldout=null"]),
                f"paths.output_dir={tmp_path}",
            ]
        )
    )
    assert off.callbacks.heldout is None


def test_the_recorded_command_of_a_run_with_a_config_dir_composes_again(tmp_path):
    (tmp_path / "my_conf" / "experiment").mkdir(parents=True)
    (tmp_path / "my_conf" / "experiment" / "tiny.yaml").write_text(
        "# @package _global_\ndefaults:\n  - synthetic\ntask_name: tiny\n"
    )
    overrides = [o for o in TINY if not o.startswith("experiment=")]
    result = unicorn_train("-cd", "my_conf", "+experiment=tiny", *overrides, "hydra.run.dir=run", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    command = json.loads((tmp_path / "run" / "provenance.json").read_text())[0]["command"]
    prog, *args = shlex.split(command)
    assert prog == "unicorn-train" and args[:2] == ["--config-dir", str(tmp_path / "my_conf")]
    again = unicorn_train("--cfg", "job", *args, cwd=tmp_path / "run")  # elsewhere: the folder is absolute
    assert again.returncode == 0 and "task_name: tiny" in again.stdout, again.stderr[-2000:]


@pytest.mark.parametrize(
    "args, refused",
    [
        (["-m", "experiment=synthetic,synthetic_wild"], True),
        (["--multirun", "+experiment=synthetic,cub", "seed=1"], True),
        (["-m", "experiment=choice(synthetic,cub)"], True),
        (["-m", "experiment=synthetic,synthetic_wild", "hydra.sweep.dir=sweep"], False),
        (["-m", "experiment=synthetic", "seed=1,2"], False),  # one experiment: one task name
        (["experiment=synthetic,synthetic_wild"], False),  # not a sweep: Hydra's own error
        (["-m", "task_name=a,b"], True),  # the other settings that name the default sweep folder
        (["-m", "paths.log_dir=x,y", "seed=1"], True),
        (["-m", "task_name=a", "seed=1,2"], False),
        (["-m", "task_name=a,b", "hydra.sweep.dir=sweep"], False),
    ],
)
def test_a_sweep_over_experiments_needs_one_folder(args, refused):
    problem = train.sweep_problem(args)
    assert (problem is not None) == refused
    if refused:
        assert "names the sweep's folder needs one folder for all its jobs, hydra.sweep.dir=DIR" in problem


def test_cfg_job_with_a_sweep_is_one_line(tmp_path: Path) -> None:
    done = unicorn_train("--cfg", "job", "-m", "+experiment=synthetic", "seed=1,2", cwd=tmp_path)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines() == [
        "unicorn-train: error: Only one of --run, --multirun, --cfg, --info and --shell_completion can be specified "
        "(Hydra runs one of these at a time: --cfg job prints one run's config, without -m and one value per key)"
    ]


def test_a_key_deep_in_a_free_mapping_is_overridden_without_a_plus(tmp_path):
    # the real-image family's camera names a fov: a focal length instead is a key the preset lacks, in the free
    # renderer mapping, one level below it
    args = ["experiment=cub", "renderer.camera.fov=null", "renderer.camera.focal_length=2.0"]
    rewritten = train.open_node_overrides(args)
    assert rewritten == ["experiment=cub", "++renderer.camera.fov=null", "++renderer.camera.focal_length=2.0"]
    typed = validate(compose_config([*rewritten, "dataset.root=/data/cub", f"paths.output_dir={tmp_path}"]))
    settings = model_config(typed)["renderer"]
    assert settings["fov"] is None and settings["focal_length"] == 2.0
    # a schema group's misspelt key is still not rewritten: Hydra names it
    assert train.open_node_overrides(["model.loss.rgb_wieght=1"]) == ["model.loss.rgb_wieght=1"]
