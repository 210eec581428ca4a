"""Mistakes on ``unicorn-train``'s command line that Hydra or Lightning report with a traceback: each is one line,
``unicorn-train: error: ...`` naming the setting, exit status 2, and nothing written. The hints name files as the
run writes them."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

from tests.support.training import TINY, error_lines, unicorn_train
from unicorn.cli.hydra_app import hydra_failure

ROOT = Path(__file__).resolve().parents[2]


def _one_error(result, cwd: Path) -> str:
    """The one ``unicorn-train: error:`` line of a refused command (exit status 2, no traceback, nothing written)."""
    errors = [line for line in error_lines(result.stderr) if line.startswith("unicorn-train: error: ")]
    assert result.returncode == 2, result.stderr[-3000:]
    assert len(errors) == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert list(cwd.iterdir()) == []
    return errors[0].removeprefix("unicorn-train: error: ")


@pytest.mark.parametrize(
    "args, override, options",
    [
        (["--cfg", "job", "experiment=null"], "experiment=null", "cub, cub_big"),
        (["+experiment=null"], "experiment=null", "synthetic, synthetic64"),
        (["model=null"], "model=null", "big, small, tiny"),
        (["dataset=null"], "dataset=null", "compcars, cub_200"),
        (["--cfg", "job", "+experiment=synthetic", "dataset=null"], "dataset=null", "shapenet_nmr, synthetic"),
    ],
)
def test_a_config_group_set_to_null_is_one_line_naming_it(tmp_path, args, override, options) -> None:
    line = _one_error(unicorn_train(*args, cwd=tmp_path), tmp_path)
    assert line.startswith(f"{override}: a config group cannot be null; choose one of its options ("), line
    assert options in line and line.endswith("), or leave the override out"), line


def test_a_null_group_hydra_reports_without_the_command_line_is_still_one_line() -> None:
    text = "Traceback (most recent call last):\n  ...\nValueError: Config group override must be a string or a list."
    assert hydra_failure(f"{text} Got NoneType") == (
        "a config group override is null: choose one of the group's options, or leave the override out"
    )
    assert hydra_failure(f"{text} Got NoneType", ["seed=1", "hydra/launcher=null"]) == (
        "hydra/launcher=null: a config group cannot be null; choose one of its options, or leave the override out"
    )


@pytest.mark.parametrize(
    "args, line",
    [
        (
            ["experiment=cub", "+family=shapenet"],
            "+family=shapenet: the config already chooses a family; write family=shapenet (without +)",
        ),
        (["+model=big"], "+model=big: the config already chooses a model; write model=big (without +)"),
        (
            ["experiment=cub", "+renderer=hard"],
            "+renderer=hard: the config already chooses a renderer; write renderer=hard (without +)",
        ),
        (
            ["+family=shapenet", "+family=real"],
            "+family=shapenet, +family=real: family is chosen more than once; give it once",
        ),
    ],
)
def test_a_group_appended_that_the_config_already_chooses_is_one_line_naming_the_override(tmp_path, args, line):
    """Not Hydra's hint about the ``override`` keyword of config files."""
    assert _one_error(unicorn_train("--cfg", "job", *args, cwd=tmp_path), tmp_path) == line


@pytest.mark.skipif(importlib.util.find_spec("torch_xla") is not None, reason="torch_xla is installed")
def test_an_accelerator_whose_package_is_missing_is_one_line(tmp_path) -> None:
    result = unicorn_train(*TINY, "trainer.accelerator=tpu", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = _one_error(result, tmp_path)
    assert line.startswith("trainer.accelerator=tpu needs a package that is not installed: Requirement 'torch_xla")


def test_the_quoting_hint_names_a_checkpoint_as_the_run_writes_it() -> None:
    from unicorn.lit.callbacks import periodic_checkpoint

    written = Path(periodic_checkpoint("run/checkpoints", 10, 2, True).format_checkpoint_name({"step": 10})).name
    line = hydra_failure("LexerNoViableAltException? mismatched input '=' expecting <EOF>")
    assert line is not None
    hint = re.search(r"""'ckpt_path="run/checkpoints/([^"]+)"'""", line)
    assert hint is not None and hint.group(1) == written, line


#: a periodic file of a run (a checkpoint, an image) as the documentation names it; not ``nonfinite-step=N.ckpt``
DOCUMENTED_STEP_FILE = re.compile(r"(?<![\w-])step=([^`\s/]+)\.(ckpt|png)")


@pytest.mark.parametrize(
    "page", ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]
)
def test_the_documentation_names_periodic_files_as_the_run_writes_them(page) -> None:
    """``step=0000010.ckpt`` (the iteration on seven digits), or the form ``step=NNNNNNN.ckpt``; never
    ``step=N.ckpt`` or ``step=10.ckpt``, names no run has."""
    wrong = [m.group(0) for m in DOCUMENTED_STEP_FILE.finditer((ROOT / page).read_text())]
    wrong = [name for name in wrong if not re.fullmatch(r"step=(\d{7}|N{7})\.(ckpt|png)", name)]
    assert not wrong, f"{page}: {wrong}"
