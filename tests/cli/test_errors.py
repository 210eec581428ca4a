"""The commands' error boundary: which failures are one line (exit 2), how they read, and that bugs keep tracebacks;
unicorn's warnings in one line."""

from __future__ import annotations

import errno
import logging
import os
import signal
import threading
import warnings

import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from unicorn.cli.errors import WARNINGS_LOGGER, expected_error, log_warnings, one_line, report_errors
from unicorn.data.common import UnreadableItemsError
from unicorn.data.images import ImageLoadError
from unicorn.errors import UnicornWarning
from unicorn.lit.diagnostics import ViewpointWarning
from unicorn.render import RenderOverflowWarning


class _Bad(Dataset):
    """Every item fails the way a bad image file does (with ``chained``: as the skip policy gives up)."""

    def __init__(self, chained: bool = False) -> None:
        self.chained = chained

    def __len__(self) -> int:
        return 4

    def __getitem__(self, index: int) -> torch.Tensor:
        error = ImageLoadError(f"photos/{index}.png", "cannot identify image file")
        if not self.chained:
            raise error
        raise UnreadableItemsError(f"4 consecutive unreadable items from index {index}, the last: {error}") from error


def _worker_error(chained: bool) -> BaseException:
    with pytest.raises(Exception) as caught:
        next(iter(DataLoader(_Bad(chained), batch_size=2, num_workers=1)))
    return caught.value


@pytest.mark.parametrize("chained", [False, True])
def test_a_dataloader_workers_error_is_its_message_not_its_traceback(chained: bool) -> None:
    err = _worker_error(chained)
    assert "Traceback" in str(err)  # torch puts the worker's traceback into the message
    assert expected_error(err) is err
    line = one_line(err)
    assert "Traceback" not in line and "File " not in line and line.endswith("(in DataLoader worker 0)")
    assert line.startswith("4 consecutive unreadable items" if chained else "cannot read image photos/0.png")


def test_a_worker_killed_from_outside_is_expected() -> None:
    err = RuntimeError("DataLoader worker (pid(s) 1234) exited unexpectedly")
    assert expected_error(err) is err


def test_hydras_instantiation_error_is_reported_by_its_cause() -> None:
    from hydra.errors import InstantiationException

    cause = ImageLoadError("a.png", "truncated")
    try:
        raise InstantiationException("Error in call to target 'x':\nImageLoadError(...)\nfull_key: dataset") from cause
    except InstantiationException as err:
        assert expected_error(err) is cause
    assert expected_error(InstantiationException("no cause")) is None


def test_disk_errors_and_lightning_misconfiguration_are_expected_bugs_are_not() -> None:
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    for err in (OSError(errno.ENOSPC, "No space left on device"), PermissionError(13, "denied", "/x")):
        assert expected_error(err) is err
    assert expected_error(MisconfigurationException("No supported gpu backend found!")) is not None
    for bug in (RuntimeError("shape mismatch"), KeyError("pytorch-lightning_version"), TypeError("x")):
        assert expected_error(bug) is None


def test_report_errors_cleans_up_then_keeps_a_bugs_traceback(capsys) -> None:
    cleaned = []

    def disk_full() -> int:
        raise OSError(errno.ENOSPC, "No space left on device while writing the output folder out")

    assert report_errors("prog", disk_full, cleanup=lambda: cleaned.append(1)) == 2
    assert (
        capsys.readouterr().err
        == "prog: error: [Errno 28] No space left on device while writing the output folder out\n"
    )

    def bug() -> int:
        raise ZeroDivisionError("bug")

    with pytest.raises(ZeroDivisionError):
        report_errors("prog", bug, cleanup=lambda: cleaned.append(2))
    assert cleaned == [1, 2]


def test_a_path_given_as_bytes_reads_as_text() -> None:
    err = OSError(errno.EROFS, "Read-only file system", os.fsencode("/runs/été/tensorboard"))
    assert one_line(err) == "[Errno 30] Read-only file system: /runs/été/tensorboard"
    renamed = OSError(errno.EXDEV, "Invalid cross-device link", b"/a", None, b"/b")
    assert one_line(renamed) == "[Errno 18] Invalid cross-device link: /a -> /b"


def test_an_expected_failure_in_a_background_thread_is_one_line(capsys, monkeypatch) -> None:
    def command() -> int:
        for error in (OSError(errno.EROFS, "Read-only file system", b"/run/events"), ZeroDivisionError("bug")):

            def fail(error: BaseException = error) -> None:
                raise error

            thread = threading.Thread(target=fail, name="writer")
            thread.start()
            thread.join()
        return 0

    passed_on = []
    monkeypatch.setattr(threading, "excepthook", lambda args: passed_on.append(args.exc_value))
    previous = threading.excepthook
    assert report_errors("prog", command) == 0
    assert threading.excepthook is previous
    assert capsys.readouterr().err == "prog: error in thread writer: [Errno 30] Read-only file system: /run/events\n"
    assert [type(e) for e in passed_on] == [ZeroDivisionError]  # a bug in a thread goes to the usual hook


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_report_errors_stops_a_command_at_a_signal_after_its_cleanup(capsys, signum) -> None:
    cleaned = []

    def signalled() -> int:
        os.kill(os.getpid(), signum)
        raise AssertionError("not reached: the signal stops the command")

    assert report_errors("prog", signalled, cleanup=lambda: cleaned.append(1)) == 128 + signum
    assert capsys.readouterr().err == f"prog: stopped by {signal.Signals(signum).name}\n"
    assert cleaned == [1]


def test_unicorns_warnings_are_logged_in_one_line_at_their_level_and_others_print_as_before(caplog) -> None:
    printed = []

    def python_prints(message, category, filename, lineno, file=None, line=None):
        printed.append((category, str(message)))

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = python_prints
        with caplog.at_level(logging.INFO, logger=WARNINGS_LOGGER), log_warnings():
            warnings.warn("some pixels dropped faces", RenderOverflowWarning, stacklevel=1)
            warnings.warn("the pose branch collapsed", ViewpointWarning, stacklevel=1)
            warnings.warn("a library's own", DeprecationWarning, stacklevel=1)
            warnings.filterwarnings("ignore", category=UnicornWarning)  # the filters still apply
            warnings.warn("filtered out", RenderOverflowWarning, stacklevel=1)
        assert warnings.showwarning is python_prints  # back after the block
    assert [(r.name, r.levelno, r.getMessage()) for r in caplog.records] == [
        (WARNINGS_LOGGER, logging.WARNING, "RenderOverflowWarning: some pixels dropped faces"),
        (WARNINGS_LOGGER, logging.ERROR, "ViewpointWarning: the pose branch collapsed"),
    ]
    assert printed == [(DeprecationWarning, "a library's own")]
