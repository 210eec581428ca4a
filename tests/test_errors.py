"""Every error a user can fix derives from :class:`unicorn.errors.UserError` and from the built-in callers catch;
signals in :func:`unicorn.errors.interrupt_on_signal` raise :class:`~unicorn.errors.Interrupted`, and wait for the
end of a :func:`~unicorn.errors.signals_held` block."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from unicorn.cli.errors import UsageError
from unicorn.config import ConfigError
from unicorn.data import DatasetError, DatasetNotFoundError, ImageLoadError
from unicorn.data.common import UnreadableItemsError
from unicorn.errors import Interrupted, UserError, interrupt_on_signal, pending_interrupt, signals_held
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


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_in_the_block_raises_interrupted_and_the_next_one_acts_as_before(signum):
    seen = []
    before = signal.signal(signum, lambda s, frame: seen.append(s))
    name = signal.Signals(signum).name
    try:
        # caught inside the block, the stop is not forgotten: the block raises it again as it ends
        with (
            pytest.raises(Interrupted, match=f"^stopped by {name} while testing$"),
            interrupt_on_signal("while testing"),
        ):
            with pytest.raises(Interrupted) as caught:
                os.kill(os.getpid(), signum)  # os.kill runs the handlers of its own process before it returns
            assert str(caught.value) == f"stopped by {name} while testing"
            assert caught.value.exit_status == 128 + signum
            os.kill(os.getpid(), signum)  # the second: the handler from before the block
        assert seen == [signum]
        os.kill(os.getpid(), signum)  # after the block: the handler from before it
        assert seen == [signum, signum]
    finally:
        signal.signal(signum, before)


def test_a_signal_whose_error_code_swallowed_still_stops_the_command(caplog):
    import logging

    class Swallowing(logging.Handler):  # as logging.Handler.handleError does, for any Exception in emit()
        def emit(self, record: logging.LogRecord) -> None:
            try:
                os.kill(os.getpid(), signal.SIGTERM)
            except Exception:
                pass

    logger = logging.getLogger("tests.swallowing")
    logger.addHandler(handler := Swallowing())
    try:
        with pytest.raises(Interrupted, match="^stopped by SIGTERM while testing$") as caught:
            with interrupt_on_signal("while testing"):
                assert pending_interrupt() is None
                logger.warning("the signal comes while this is written")
                late = pending_interrupt("before the first iteration")  # what training asks before it starts
                assert str(late) == "stopped by SIGTERM before the first iteration" and late.exit_status == 143
                with interrupt_on_signal("inside"):  # an inner block neither sees it as its own nor forgets it
                    pass
                assert pending_interrupt() is not None
        assert caught.value.exit_status == 143
    finally:
        logger.removeHandler(handler)
    assert pending_interrupt() is None  # the block is over


def test_the_handlers_from_before_the_block_are_back_after_it():
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    with interrupt_on_signal("while testing"):
        assert all(signal.getsignal(s) is not h for s, h in before.items())
    assert {s: signal.getsignal(s) for s in before} == before
    with pytest.raises(ValueError, match="boom"), interrupt_on_signal("while testing"):
        raise ValueError("boom")
    assert {s: signal.getsignal(s) for s in before} == before


def test_signals_held_wait_for_the_end_of_the_block_and_come_once_each_in_order():
    seen = []

    def record(signum, frame):
        seen.append(signum)

    before = {s: signal.signal(s, record) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        with signals_held():
            for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGTERM):
                os.kill(os.getpid(), signum)
            assert seen == []
        assert seen == [signal.SIGTERM, signal.SIGINT]
        with pytest.raises(ValueError, match="boom"), signals_held():
            os.kill(os.getpid(), signal.SIGINT)
            raise ValueError("boom")
        assert seen == [signal.SIGTERM, signal.SIGINT, signal.SIGINT]
        assert all(signal.getsignal(s) is record for s in before)
        os.kill(os.getpid(), signal.SIGTERM)  # after the block: the handler from before it, at once
        assert seen[-1] == signal.SIGTERM and len(seen) == 4
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


def test_signals_held_in_interrupt_on_signal_raise_interrupted_at_the_end_of_the_block():
    done = []
    with pytest.raises(Interrupted, match="stopped by SIGTERM while testing"), interrupt_on_signal("while testing"):
        with signals_held():
            os.kill(os.getpid(), signal.SIGTERM)
            done.append("the block's last step")
        done.append("not reached")
    assert done == ["the block's last step"]


def test_a_signal_whose_error_became_another_still_stops_the_command():
    def read(path: str) -> None:  # a reader that turns whatever fails in it into its own error, as loaders do
        try:
            os.kill(os.getpid(), signal.SIGTERM)
        except Exception as err:
            raise ValueError(f"cannot read {path}: {err}") from err

    with pytest.raises(Interrupted, match="^stopped by SIGTERM while reading$") as caught:
        with interrupt_on_signal("while reading"):
            read("cameras.npz")
    assert caught.value.exit_status == 143 and isinstance(caught.value.__cause__, ValueError)
    with pytest.raises(ValueError, match="no signal"):  # without a signal, errors pass as they are
        with interrupt_on_signal("while reading"):
            raise ValueError("no signal")


def test_open3d_that_cannot_load_names_the_library_it_needs(monkeypatch) -> None:
    import importlib.abc
    import sys

    from unicorn.errors import MissingPackageError, import_open3d

    class NoLibusb(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "open3d":  # what its wheel's import says on a machine without libusb
                raise OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")
            return None

    monkeypatch.delitem(sys.modules, "open3d", raising=False)
    monkeypatch.setattr(sys, "meta_path", [NoLibusb(), *sys.meta_path])
    with pytest.raises(MissingPackageError, match=r"libusb-1\.0\.so\.0.*apt-get install libusb-1\.0-0") as err:
        import_open3d()
    assert "\n" not in str(err.value)
    monkeypatch.setitem(sys.modules, "open3d", None)  # not installed at all
    with pytest.raises(MissingPackageError, match="pip install open3d"):
        import_open3d()


def test_a_second_signal_while_a_command_sets_up_stops_it_at_once_and_says_so():
    # the first is noted for the command to put its folders back; the second is the user's "now"
    script = (
        "import os, signal\n"
        "from unicorn.errors import defer_stop_signals, pending_interrupt\n"
        "defer_stop_signals('prog')\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "print(pending_interrupt('before training'), flush=True)\n"
        "os.kill(os.getpid(), signal.SIGINT)\n"
        "print('still running')\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 128 + signal.SIGINT
    assert done.stdout == "stopped by SIGTERM before training\n"
    assert done.stderr == "prog: stopped by SIGINT at once (signalled twice while setting up)\n"


def test_a_stop_signal_ignored_from_the_start_stays_ignored():
    # a script's background job is started ignoring Ctrl-C: the command's handlers leave SIGINT so, and SIGTERM stops it
    script = (
        "import os, signal\n"
        "from unicorn.errors import IGNORED_AT_START, interrupt_on_signal\n"
        "print(sorted(signal.Signals(s).name for s in IGNORED_AT_START), flush=True)\n"
        "with interrupt_on_signal('while testing'):\n"
        "    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    print('SIGINT ignored', flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    print('still running')\n"
    )

    def ignore_ctrl_c():
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, preexec_fn=ignore_ctrl_c
    )
    assert done.stdout == "['SIGINT']\nSIGINT ignored\n"
    assert done.returncode == 1 and done.stderr.rstrip().endswith("Interrupted: stopped by SIGTERM while testing")
