"""The Python examples of the README and the docs run as written, page by page (each page's blocks in order, in one
namespace, as a reader would paste them), in a folder holding the files they name; the documented
``unicorn-train`` command lines compose and validate, those of the other commands parse, and the config keys and
package names the prose gives exist."""

from __future__ import annotations

import importlib
import json
import re
import shlex
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from tests.support.evaluation import IMAGE_SIZE, tiny_checkpoint, write_inputs
from unicorn.render import RENDERERS

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def _checkpoint_at(relative: str) -> Callable[[Path], dict]:
    """A page that loads a trained checkpoint from ``relative``: a tiny one is there."""

    def prepare(folder: Path) -> dict:
        tiny_checkpoint(folder / relative)
        return {}

    return prepare


def _reconstruction(folder: Path) -> dict:
    """docs/reconstruct.md: ``model.ckpt``, ``unicorn-reconstruct``'s outputs for ``car.png``, and the images
    that ``refine`` is given."""
    from unicorn.cli.reconstruct import main

    tiny_checkpoint(folder / "model.ckpt")
    shutil.copy(write_inputs(folder / "inputs")["cutout"], folder / "car.png")
    args = ["model.ckpt", "car.png", "--out", "reconstructions", "--device", "cpu", "--quiet"]
    assert main([*args, "--view-size", "32", "--turntable-frames", "2", "--strip-views", "2"]) == 0
    return {"images": torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE)}


#: every page with Python examples, and what its examples expect to find (files, names defined before them)
PAGES: dict[str, Callable[[Path], dict]] = {
    "README.md": lambda folder: {},
    "docs/getting-started.md": _checkpoint_at("outputs/synthetic/runs/<time>/checkpoints/last.ckpt"),
    "docs/model.md": lambda folder: {},
    "docs/reconstruct.md": _reconstruction,
    "docs/renderer.md": lambda folder: {},
}


def _blocks(page: str) -> list[tuple[int, str]]:
    text = (ROOT / page).read_text()
    return [(text[: m.start()].count("\n") + 2, m.group(1)) for m in BLOCK.finditer(text)]


def test_every_page_with_python_examples_is_run() -> None:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    with_examples = {str(p.relative_to(ROOT)) for p in pages if _blocks(str(p.relative_to(ROOT)))}
    assert with_examples == set(PAGES)


@pytest.mark.parametrize("page", sorted(PAGES))
def test_the_python_examples_of_a_page_run_as_written(page: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": f"example_{page}", **PAGES[page](tmp_path)}
    registered = set(RENDERERS.names())
    try:
        for line, code in _blocks(page):
            exec(compile(code, f"{page}:{line}", "exec"), namespace)  # the project's own examples
    finally:
        for name in set(RENDERERS.names()) - registered:  # a backend an example registers stays in its page
            RENDERERS.remove(name)
    if page == "docs/reconstruct.md":  # what the comment says: the pose read back is the written one
        pose = json.loads((tmp_path / "reconstructions" / "car" / "pose.json").read_text())
        assert torch.allclose(namespace["R"], torch.tensor(pose["R"]), atol=1e-5)
        assert torch.allclose(namespace["T"], torch.tensor(pose["T"]), atol=1e-5)
        # the OpenCV pixels: where R, T and the focal length put the vertices, through the frame (pixel centres at 0)
        view = torch.tensor(namespace["vertices"]) @ torch.tensor(pose["R"]).double() + torch.tensor(pose["T"]).double()
        ndc = pose["camera"]["focal_length_ndc"] * view[:, :2] / view[:, 2:]
        frame = pose["frame"]
        u = frame["x"] + (1 - ndc[:, 0]) / 2 * frame["width"] - 0.5
        v = frame["y"] + (1 - ndc[:, 1]) / 2 * frame["height"] - 0.5
        assert torch.allclose(torch.tensor(namespace["uv"]), torch.stack([u, v], dim=-1), atol=1e-4)


#: where the documented command lines are
COMMAND_PAGES = ["README.md", *(str(p.relative_to(ROOT)) for p in sorted((ROOT / "docs").rglob("*.md")))]
COMMAND_PAGES += ["experiments/README.md"]
SHELL_BLOCK = re.compile(r"^```(?:bash|sh|console)\n(.*?)^```", re.S | re.M)
#: the placeholders of the command lines, and values that stand for them
PLACEHOLDERS = {"<time>": "2026-11-30_08-00-00-000000", "seed=S": "seed=0"}


def _command_lines(program: str) -> list[tuple[str, list[str]]]:
    """Every ``program`` command line of the documentation's shell blocks (its arguments, placeholders given
    values), with where it is."""
    found = []
    for page in COMMAND_PAGES:
        text = (ROOT / page).read_text()
        for m in SHELL_BLOCK.finditer(text):
            for number, line in enumerate(m.group(1).replace("\\\n", " ").splitlines()):
                for placeholder, value in PLACEHOLDERS.items():
                    line = line.replace(placeholder, value)
                words = shlex.split(line, comments=True)
                if words and words[0] == program:
                    where = f"{page}, block at line {text[: m.start()].count(chr(10)) + 1}, line {number + 1}"
                    found.append((where, words[1:]))
    return found


def _train_commands() -> list[tuple[str, list[str]]]:
    """The overrides of every documented ``unicorn-train`` command line that names a run (a sweep's values: the
    first), with where it is."""
    found = []
    for where, args in _command_lines("unicorn-train"):
        if {"-cd", "--help", "--version"} & set(args):
            continue
        overrides = [w for w in args if "=" in w and not w.startswith(("-", "hydra.", "hydra/"))]
        if "-m" in args:
            overrides = [re.sub(r"=([^,{\[]*),.*", r"=\1", w) for w in overrides]  # a sweep's first job
        found.append((where, overrides))
    return found


def test_the_documented_training_commands_compose_and_validate(tmp_path: Path) -> None:
    from tests.support.training import compose_config
    from unicorn.cli.train import experiment_overrides
    from unicorn.config import validate

    commands = _train_commands()
    assert len(commands) > 20
    failures = []
    for where, overrides in commands:
        try:
            validate(compose_config([*experiment_overrides(overrides), f"paths.output_dir={tmp_path}"]))
        except Exception as err:  # every command is tried; the failures are listed together
            failures.append(f"{where}: {' '.join(overrides)}: {type(err).__name__}: {err}")
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("program", ["unicorn-eval", "unicorn-reconstruct", "unicorn-data"])
def test_the_documented_command_lines_parse(program: str, capsys) -> None:
    parser = importlib.import_module(f"unicorn.cli.{program.removeprefix('unicorn-')}").build_parser()
    lines = _command_lines(program)
    assert lines
    failures = []
    for where, args in lines:
        try:
            parser.parse_args(args)
        except SystemExit:
            failures.append(f"{where}: {program} {' '.join(args)}: {capsys.readouterr().err.strip().splitlines()[-1]}")
    assert not failures, "\n".join(failures)


#: a documented override in the prose: `key.path=value`, or `+key.path=value` for a key the config may add
INLINE_OVERRIDE = re.compile(r"`(\+?)([a-z_][a-z0-9_]*(?:\.[a-z0-9_]+)+)=([^`\s]*)`")


def test_the_config_keys_the_documentation_names_exist(tmp_path: Path) -> None:
    """Each `key.path=value` of the prose is a key of some experiment's training config (a model config key,
    `loss.perceptual`, as the training config's `model.` key); each `+key.path=value` composes and validates in
    the main job's config or its wild mode's (an upper-case placeholder value, N, as 2 ** 40)."""
    from omegaconf import OmegaConf

    from tests.support.training import compose_config
    from unicorn.config import validate
    from unicorn.resources import config_dir

    experiments = sorted(p.stem for p in (config_dir() / "experiment").glob("*.yaml"))
    configs = [validate(compose_config([f"experiment={e}", f"paths.output_dir={tmp_path}"])) for e in experiments]
    top = set(configs[0])
    named = {
        (plus, key if key.split(".")[0] in top else f"model.{key}", str(2**40) if value.isupper() else value, page)
        for page in COMMAND_PAGES
        for plus, key, value in INLINE_OVERRIDE.findall((ROOT / page).read_text())
        if not key.startswith("hydra.")
    }
    assert len(named) > 40
    failures = []
    for plus, key, value, page in sorted(named):
        if not plus:
            if all(OmegaConf.select(cfg, key, default=KeyError) is KeyError for cfg in configs):
                failures.append(f"{page}: {key}: no such key")
            continue
        errors = []
        for experiment in ("synthetic", "synthetic_wild"):  # the main job's config, or its wild mode's (roll, shift)
            try:
                validate(
                    compose_config([f"experiment={experiment}", f"+{key}={value}", f"paths.output_dir={tmp_path}"])
                )
            except Exception as err:  # every key is tried; the failures are listed together
                errors.append(f"{type(err).__name__}: {err}")
        if len(errors) == 2:
            failures.append(f"{page}: +{key}={value}: {errors[0]}")
    assert not failures, "\n".join(failures)


#: a Python name of the package in the prose: `unicorn.module.name` or `unicorn.module.function(...)`
PACKAGE_NAME = re.compile(r"`(unicorn(?:\.[A-Za-z_][A-Za-z0-9_]*)+)(?:\([^`]*\))?`")
#: names in that form that are not Python names: the entry-point groups, the warnings' logger
NOT_PYTHON = {"unicorn.renderers", "unicorn.plugins", "unicorn.warnings"}


def _resolves(name: str) -> bool:
    """Whether ``name`` is a module of the package or an attribute reached from one."""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        try:
            found = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        for attribute in parts[split:]:
            if not hasattr(found, attribute):
                return False
            found = getattr(found, attribute)
        return True
    return False


def test_the_package_names_the_documentation_gives_exist() -> None:
    named = {(name, page) for page in COMMAND_PAGES for name in PACKAGE_NAME.findall((ROOT / page).read_text())}
    assert len(named) > 50
    missing = sorted(f"{page}: {name}" for name, page in named if name not in NOT_PYTHON and not _resolves(name))
    assert not missing, "\n".join(missing)
