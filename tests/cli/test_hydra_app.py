"""``HydraApp`` hands Hydra the user's command line with ``hydra.output_subdir=null`` added, in any order of
options and overrides (Hydra's own argument parser is the oracle)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hydra._internal.utils import get_args_parser

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
