"""What ``--help`` says an option defaults to is what the command does when the option is left out."""

from __future__ import annotations

import argparse

import pytest

from unicorn.cli import data as data_cli
from unicorn.cli import eval as eval_cli


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@pytest.mark.parametrize(("command", "required"), [("synth", []), ("check", ["synthetic", "--root", "DIR"])])
def test_unicorn_data_help_names_every_default(command: str, required: list[str]) -> None:
    """Each option of ``unicorn-data synth`` / ``check`` with a default shows the value the parser gives it."""
    parser = data_cli.build_parser()
    sub = _subparser(parser, command)
    parsed = vars(parser.parse_args([command, *required]))
    help_text = " ".join(sub.format_help().split())  # argparse wraps the lines
    defaults = {
        a.option_strings[0]: parsed[a.dest]
        for a in sub._actions
        if a.option_strings and all(a.default is not v for v in (None, False, argparse.SUPPRESS))  # 0 counts
    }
    assert defaults  # --models, --size, --views ... (synth); --split (check)
    missing = [f"{option} {value}" for option, value in defaults.items() if f"(default: {value})" not in help_text]
    assert not missing
    assert all(a.help for a in sub._actions if a.option_strings)  # no option without a word of help


def test_unicorn_eval_help_names_the_training_runs_categories_and_root_as_defaults() -> None:
    """Without --root and --categories, unicorn-eval takes the training run's (tests/cli/test_eval_cli.py,
    test_dataset_of_the_training_run); the help says so rather than "default: all"."""
    help_text = " ".join(eval_cli.build_parser().format_help().split())
    help_text = help_text[help_text.index("options:") :]  # past the usage line
    for option in ("--root ROOT", "--categories CATEGORIES"):
        text = help_text[help_text.index(option) : help_text.index("--", help_text.index(option) + 2)]
        assert "default: the training run's" in text, text
