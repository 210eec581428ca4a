"""Every error a user can fix derives from :class:`unicorn.errors.UserError` and from the built-in callers catch."""

from __future__ import annotations

import pytest

from unicorn.cli.errors import UsageError
from unicorn.config import ConfigError
from unicorn.data import DatasetError, DatasetNotFoundError, ImageLoadError
from unicorn.data.common import UnreadableItemsError
from unicorn.errors import UserError
from unicorn.io import CheckpointError, CorruptCheckpointError, UnsafeCheckpointError
from unicorn.lit import NonFiniteLossError


@pytest.mark.parametrize(
    ("cls", "builtin"),
    [
        (ConfigError, ValueError),
        (CheckpointError, ValueError),
        (UnsafeCheckpointError, ValueError),
        (CorruptCheckpointError, ValueError),
        (DatasetError, ValueError),
        (DatasetNotFoundError, FileNotFoundError),
        (ImageLoadError, RuntimeError),
        (UnreadableItemsError, RuntimeError),
        (NonFiniteLossError, FloatingPointError),
        (UsageError, ValueError),
    ],
)
def test_user_errors(cls: type, builtin: type) -> None:
    assert issubclass(cls, UserError) and issubclass(cls, builtin)


def test_unicorn_data_reports_in_one_line(tmp_path, capsys) -> None:
    from unicorn.cli.data import main

    assert main(["check", "cub_200", "--root", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-data: error: CUB-200-2011 root not found") and err.count("\n") == 1
    assert main(["check", "shapenet_nmr", "--root", str(tmp_path), "--categories", "teapot"]) == 2
    assert capsys.readouterr().err.startswith("unicorn-data: error: ")
    with pytest.raises(Exception, match="root not found"):
        main(["check", "cub_200", "--root", str(tmp_path / "nothing"), "--debug"])
