"""Every command answers ``--version`` (unicorn-train's is tested with its --help in test_train_cli.py)."""

from __future__ import annotations

import pytest

from unicorn import __version__
from unicorn.cli import data as data_cli
from unicorn.cli import eval as eval_cli
from unicorn.cli import reconstruct as reconstruct_cli


@pytest.mark.parametrize(
    ("main", "prog"),
    [(eval_cli.main, "unicorn-eval"), (reconstruct_cli.main, "unicorn-reconstruct"), (data_cli.main, "unicorn-data")],
)
def test_version(main, prog, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"{prog} (unicorn3d) {__version__}"
