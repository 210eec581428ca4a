"""``HydraApp`` hands Hydra the user's command line with ``hydra.output_subdir=null`` added, in any order of
options and overrides (Hydra's own argument parser is the oracle); it refuses a sweep's folder that holds an earlier
sweep or another sweep under way, and a command it stops while it sets up leaves the folders as they were."""

from __future__ import annotations

import os
import re
import shlex
import signal
import sys
from pathlib import Path

import pytest
from hydra._internal.utils import get_args_parser
from omegaconf import OmegaConf

from tests.support.training import TINY, error_lines, snapshot, unicorn_train
from unicorn.cli.hydra_app import APP_OVERRIDES, HydraApp

COMMAND_LINES = [
    [],
    ["experiment=cub"],
    ["experiment=cub", "--cfg", "job"],
    ["--cfg", "job", "experiment=cub", "seed=2"],
    ["-m", "seed=0,1", "--cfg", "job"],
    ["-cd", "my_conf", "experiment=mine", "--info", "defaults"],
    ["--info", "defaults", "~callbacks.images"],
    ["--cfg", "job", "~callbacks.images", "--package", "model"],
    ["--config-dir=my_conf", "+experiment=mine", "--resolve"],
    ["--info"],  # no topic: the app's overrides were taken for it
    ["--cfg", "job", "--info"],
]


@pytest.mark.parametrize("args", COMMAND_LINES, ids=lambda a: " ".join(a) or "none")
def test_hydra_parses_the_users_options_and_overrides_unchanged(args):
    expected = get_args_parser().parse_args(args)
    parsed = get_args_parser().parse_args(HydraApp("unicorn-train", Path("."), "train").hydra_args(args))
    assert parsed.overrides == [*APP_OVERRIDES, *expected.overrides]
    assert {k: v for k, v in vars(parsed).items() if k != "overrides"} == {
        k: v for k, v in vars(expected).items() if k != "overrides"
    }


def test_a_users_output_subdir_is_kept_for_the_record():
    app = HydraApp("unicorn-train", Path("."), "train")
    assert app.hydra_args(["hydra.output_subdir=rec", "seed=1"]) == [*APP_OVERRIDES, "seed=1"]
    assert app.record_subdir == "rec"


@pytest.mark.parametrize("value", ["~/runs/a", '"~/runs/a"', "'~/runs/a'"], ids=["plain", "double", "single"])
@pytest.mark.parametrize("key", ["hydra.run.dir", "hydra.sweep.dir", "+hydra.run.dir"])
def test_a_run_folder_under_the_home_folder_is_expanded_as_in_a_shell(monkeypatch, key, value):
    monkeypatch.setenv("HOME", "/home/me")
    quote = value[0] if value[0] in "'\"" else ""
    args = HydraApp("unicorn-train", Path("."), "train").hydra_args([f"{key}={value}", "seed=1"])
    assert args == [*APP_OVERRIDES, f"{key}={quote}/home/me/runs/a{quote}", "seed=1"]  # not ./~/runs/a
    assert HydraApp("unicorn-train", Path("."), "train").hydra_args(["hydra.run.dir=a~b"])[-1] == "hydra.run.dir=a~b"


@pytest.mark.parametrize("arg", ["hydra.run.dir=", "hydra.run.dir=''", '+hydra.sweep.dir=" "'])
def test_a_run_folder_left_empty_is_refused_not_taken_for_the_current_folder(tmp_path, monkeypatch, capsys, arg):
    # hydra.run.dir=$RUN with RUN unset: Hydra would train in the folder the command was started from
    monkeypatch.setattr(sys, "argv", ["unicorn-train"])
    monkeypatch.chdir(tmp_path)
    app = HydraApp("unicorn-train", tmp_path / "conf", "train")
    with pytest.raises(SystemExit) as stop:
        app.run(lambda cfg: pytest.fail("the task ran"), ["seed=1", arg])
    name = arg.lstrip("+").split("=")[0]
    assert stop.value.code == 2
    assert capsys.readouterr().err == (
        f"unicorn-train: error: {name} is empty: give the folder, or leave {name} out for a new folder under "
        "paths.log_dir\n"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "keys"),
    [
        (["seed=0,1", "optim.lr=2e-4"], {"seed"}),
        (["-m", "+x=choice(1,2)", "y=range(3)", "~z=1"], {"x", "y"}),
        (["model.stages.texture=[2,4,8,16]", "a={b: 1, c: 2}", "s='1,2'"], set()),  # a list, a dict, a string
        (["model.stages.texture=[2,4],[4,8]", "--cfg", "job"], {"model.stages.texture"}),
    ],
)
def test_the_keys_a_command_line_sweeps(args, keys):
    from unicorn.cli.hydra_app import swept_keys

    assert swept_keys(args) == keys


def test_a_new_sweep_into_an_earlier_sweeps_folder_is_refused_and_keeps_its_record(synthetic_cache, tmp_path):
    sweep = tmp_path / "sweep"
    (sweep / "0").mkdir(parents=True)
    (sweep / "0" / "notes.txt").write_text("mine")
    (sweep / "multirun.yaml").write_text("the record of an earlier sweep")
    before = snapshot(sweep)
    args = ["-m", *TINY, "trainer.max_steps=1", "seed=5,6", f"hydra.sweep.dir={sweep}"]
    refused = unicorn_train(*args, cwd=tmp_path)
    assert refused.returncode == 2, refused.stderr[-3000:]
    assert error_lines(refused.stderr) == [
        f"unicorn-train: error: {sweep} holds an earlier sweep (multirun.yaml, Hydra's record of it); go on with it "
        "with ckpt_path=last, replace its runs with overwrite=true, or sweep elsewhere (hydra.sweep.dir=...)"
    ]
    assert snapshot(sweep) == before
    # going on with it: the jobs it had not reached run, and the record is the command's that went on
    went_on = unicorn_train(*args, "ckpt_path=last", cwd=tmp_path)
    assert went_on.returncode == 0, went_on.stderr[-3000:]
    assert all((sweep / job / "checkpoints" / "last.ckpt").is_file() for job in ("0", "1"))
    assert (sweep / "0" / "notes.txt").read_text() == "mine"
    assert "seed=5,6" in (sweep / "multirun.yaml").read_text()
    assert not (sweep / ".unicorn-train.lock").exists()  # let go


@pytest.mark.parametrize("swept", ["seed=1,2", "overwrite=true,false"])
def test_a_sweep_into_a_runs_folder_is_refused_and_the_run_still_resumes(synthetic_cache, tmp_path, swept):
    """Hydra's record of the sweep (``multirun.yaml``) in a run's folder would make it a sweep's folder, which a
    resume of the run refuses."""
    run = tmp_path / "run"
    trained = unicorn_train(*TINY, "trainer.max_steps=1", f"hydra.run.dir={run}", cwd=tmp_path)
    assert trained.returncode == 0, trained.stderr[-3000:]
    before = snapshot(run)
    refused = unicorn_train("-m", *TINY, "trainer.max_steps=1", swept, f"hydra.sweep.dir={run}", cwd=tmp_path)
    assert refused.returncode == 2, refused.stderr[-3000:]
    assert error_lines(refused.stderr) == [
        f"unicorn-train: error: {run} holds a run (provenance.json), not a sweep: a sweep's folder holds its jobs' "
        "folders, and its record there would keep the run from being resumed; sweep elsewhere (hydra.sweep.dir=...)"
    ]
    assert snapshot(run) == before
    resumed = unicorn_train(*TINY, "trainer.max_steps=2", f"hydra.run.dir={run}", "ckpt_path=last", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]


def test_a_sweep_into_the_folder_of_a_sweep_under_way_is_refused(synthetic_cache, tmp_path):
    from unicorn.io.run_folder import lock_folder

    sweep = tmp_path / "sweep"
    lock = lock_folder(sweep)  # the sweep under way
    before = snapshot(sweep)
    try:
        refused = unicorn_train("-m", *TINY, "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    finally:
        after = snapshot(sweep)
        lock.release()
    assert refused.returncode == 2, refused.stderr[-3000:]
    [line] = error_lines(refused.stderr)
    assert line.startswith(f"unicorn-train: error: {sweep} is in use by another unicorn-train (pid {os.getpid()} ")
    assert line.endswith("; wait for it to end or train elsewhere (hydra.sweep.dir=...)")
    assert after == before


def _signalled_twice_while_setting_up() -> None:
    """unicorn-train's main() signalled twice (SIGTERM) after Hydra made the job's folder and opened its log
    (``UNICORN_TEST_AT=hydra``), or in the task once it locked the folder (``task``)."""
    from unicorn.cli import train
    from unicorn.cli.hydra_app import NoteExistingFolders
    from unicorn.io import run_folder

    def twice() -> None:
        os.kill(os.getpid(), signal.SIGTERM)  # noted: the command puts its folder back, then stops
        os.kill(os.getpid(), signal.SIGTERM)  # at once

    if os.environ["UNICORN_TEST_AT"] == "hydra":
        NoteExistingFolders.on_job_start = lambda self, config, **kwargs: twice()
    else:
        noted = run_folder.FolderChanges.__init__

        def note(self, *args, **kwargs):
            noted(self, *args, **kwargs)
            twice()

        run_folder.FolderChanges.__init__ = note
    train.main()


@pytest.mark.parametrize("at", ["hydra", "task"])
@pytest.mark.parametrize("where", ["new", "mine", "sweep", "elsewhere"])
def test_a_command_signalled_twice_while_it_sets_up_stops_at_once_and_leaves_the_folders_as_they_were(
    tmp_path, monkeypatch, where, at
):
    monkeypatch.setenv("UNICORN_TEST_AT", at)
    if where == "mine":
        (tmp_path / "mine").mkdir()
        (tmp_path / "mine" / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    folder = f"hydra.run.dir={tmp_path / 'outputs' / 'run'}" if where == "new" else f"hydra.run.dir={tmp_path / 'mine'}"
    sweep = ["-m", *TINY, "seed=1,2", f"hydra.sweep.dir={tmp_path / 'outputs' / 'sweep'}"]
    args = sweep if where == "sweep" else [*TINY, folder]
    if where == "elsewhere":  # a paths.output_dir beside Hydra's folder (refused once built): neither is left
        args.append(f"paths.output_dir={tmp_path / 'elsewhere'}")
    stopped = unicorn_train(*args, cwd=tmp_path, entry=f"{__name__}:_signalled_twice_while_setting_up")
    assert stopped.returncode == 143, stopped.stderr[-3000:]
    stops = [line for line in error_lines(stopped.stderr) if line.startswith("unicorn-train:")]
    assert stops == ["unicorn-train: stopped by SIGTERM at once (signalled twice while setting up)"]
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize(
    "arg", ["paths.output_dir=runs/café", "paths.output_dir=runs/a#b", "ckpt_path=run/checkpoints/step=0000010.ckpt"]
)
def test_the_quoting_hint_quotes_the_users_override_as_hydra_reads_it(tmp_path, arg):
    """The one line for an override Hydra's grammar refuses shows that override quoted; given back to the shell as
    shown, Hydra reads the value the user meant (Hydra's composed config is the oracle)."""
    refused = unicorn_train(*TINY, arg, "--cfg", "job", cwd=tmp_path)
    (line,) = error_lines(refused.stderr)
    assert refused.returncode == 2 and line.startswith("unicorn-train: error: "), refused.stderr[-3000:]
    hint = re.search(r"must be quoted for Hydra: (.+)\)$", line)
    assert hint is not None, line
    (quoted,) = shlex.split(hint.group(1))  # as a shell hands it over
    read = unicorn_train(*TINY, quoted, "--cfg", "job", cwd=tmp_path)
    assert read.returncode == 0, read.stderr[-3000:]
    key, _, value = arg.partition("=")
    assert OmegaConf.select(OmegaConf.create(read.stdout), key) == value
