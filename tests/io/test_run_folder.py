"""A training run's folder: which checkpoint ``ckpt_path`` names, what a resume would replace, the folder's lock,
undoing what a failed run wrote."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.checkpoints import deflated_torch_file
from unicorn.errors import UserError
from unicorn.io.run_folder import (
    LOCK_NAME,
    RUN_PROVENANCE,
    FolderChanges,
    RunFolderBusyError,
    RunFolderError,
    checkpoint_step,
    lock_folder,
    plan_folder,
    plan_sweep_folder,
    put_back_set_up,
    resolve_ckpt,
    run_of_checkpoint,
    set_aside,
)


def test_ckpt_path_must_be_a_file(tmp_path) -> None:
    with pytest.raises(IsADirectoryError, match=rf"ckpt_path: {tmp_path} is a directory, not a checkpoint file"):
        resolve_ckpt(str(tmp_path), tmp_path / "checkpoints")
    with pytest.raises(FileNotFoundError, match="ckpt_path: no checkpoint file at"):
        resolve_ckpt(str(tmp_path / "missing.ckpt"), tmp_path / "checkpoints")
    with pytest.raises(UserError):
        resolve_ckpt(str(tmp_path), tmp_path / "checkpoints")
    (tmp_path / "a.ckpt").write_bytes(b"x")
    assert resolve_ckpt(str(tmp_path / "a.ckpt"), tmp_path / "checkpoints") == str(tmp_path / "a.ckpt")
    assert resolve_ckpt("last", tmp_path / "checkpoints") is None  # no last.ckpt yet: from scratch
    with pytest.raises(UserError, match=r"^ckpt_path is empty: name a checkpoint file, or last"):
        resolve_ckpt("", tmp_path / "checkpoints")  # was taken for the current directory


def test_last_in_a_folder_without_a_run_warns_that_it_resumes_nothing(tmp_path, caplog) -> None:
    with caplog.at_level(logging.INFO, logger="unicorn.train"):
        assert resolve_ckpt("last", tmp_path / "new" / "checkpoints") is None
        (tmp_path / "run" / "checkpoints").mkdir(parents=True)  # a run killed before its first checkpoint
        assert resolve_ckpt("last", tmp_path / "run" / "checkpoints") is None
    levels = [(r.levelname, r.getMessage().split(",")[0]) for r in caplog.records]
    assert levels == [
        ("WARNING", f"ckpt_path=last: {tmp_path / 'new'} holds no run to resume"),
        ("INFO", f"ckpt_path=last: no {tmp_path / 'run' / 'checkpoints' / 'last.ckpt'} yet"),
    ]


def test_last_in_a_resumed_sweep_trains_the_jobs_it_had_not_reached_without_a_warning(
    tmp_path, caplog, monkeypatch
) -> None:
    """``-m ... hydra.sweep.dir=<sweep> ckpt_path=last`` named the sweep's folder: a job folder it had not reached
    is said at INFO, not warned about with a hint to name the folder; a sweep of no run yet is still warned."""
    from unicorn.io import run_folder

    monkeypatch.setattr(run_folder, "in_sweep", lambda: True)
    sweep = tmp_path / "sweep"
    with caplog.at_level(logging.INFO, logger="unicorn.train"):
        assert resolve_ckpt("last", sweep / "0" / "checkpoints") is None  # nothing there: a new folder?
        (sweep / "0").mkdir(parents=True)
        (sweep / "0" / RUN_PROVENANCE).write_text("{}")  # job 0 ran
        assert resolve_ckpt("last", sweep / "1" / "checkpoints") is None
    levels = [(r.levelname, r.getMessage().split(" (")[0]) for r in caplog.records]
    assert levels == [
        ("WARNING", f"ckpt_path=last: {sweep / '0'} holds no run to resume, training from scratch"),
        ("INFO", f"ckpt_path=last: {sweep / '1'} holds no run yet"),
    ]
    assert "name its folder: hydra.sweep.dir=<sweep dir>" in caplog.records[0].getMessage()


def test_last_without_last_ckpt_is_the_newest_step_file_when_none_is_written(tmp_path) -> None:
    checkpoints = tmp_path / "checkpoints"
    checkpoints.mkdir()
    for name in ("step=0000005.ckpt", "step=0000010.ckpt", "nonfinite-step=0000012.ckpt"):
        (checkpoints / name).write_bytes(b"x")
    assert resolve_ckpt("last", checkpoints, save_last=False) == str(checkpoints / "step=0000010.ckpt")
    # a run writing last.ckpt killed before its first one: started again (its logs lag the step file)
    assert resolve_ckpt("last", checkpoints, save_last=True) is None
    (checkpoints / "last.ckpt").write_bytes(b"x")
    assert resolve_ckpt("last", checkpoints, save_last=True) == str(checkpoints / "last.ckpt")
    # save_last=false: last.ckpt is a signal's, older than the step files written after it was resumed
    assert resolve_ckpt("last", checkpoints, save_last=False) == str(checkpoints / "step=0000010.ckpt")


def test_a_resume_from_an_earlier_checkpoint_names_the_later_ones(tmp_path) -> None:
    checkpoints = tmp_path / "checkpoints"
    checkpoints.mkdir()
    for name in ("step=0000005.ckpt", "step=0000010.ckpt", "step=0000020.ckpt"):
        (checkpoints / name).write_bytes(b"x")
    (checkpoints / "last.ckpt").write_bytes(b"unreadable: counts as later")
    earlier = str(checkpoints / "step=0000010.ckpt")
    with pytest.raises(RunFolderError, match=r"step=0000020\.ckpt, checkpoints/last\.ckpt; pass overwrite=true"):
        plan_folder(tmp_path, earlier, earlier, overwrite=False)
    assert plan_folder(tmp_path, earlier, earlier, overwrite=True) == []  # the resumed run deletes them itself
    assert plan_folder(tmp_path, "last", str(checkpoints / "last.ckpt"), overwrite=False) == []


def test_overwrite_beside_ckpt_path_last_resumes_and_says_it_is_not_used(tmp_path, caplog) -> None:
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"x")
    with caplog.at_level(logging.WARNING, logger="unicorn.train"):
        assert plan_folder(tmp_path, "last", str(tmp_path / "checkpoints" / "last.ckpt"), overwrite=True) == []
    assert [r.getMessage() for r in caplog.records] == [
        f"overwrite=true is not used: ckpt_path=last resumes the run {tmp_path} holds (drop ckpt_path to replace it)"
    ]


def _finished_run(folder: Path) -> Path:
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "csv").mkdir()
    for name in ("checkpoints/last.ckpt", "checkpoints/step=0000004.ckpt", "csv/metrics.csv", "config.yaml"):
        (folder / name).write_text("the run's")
    return folder


def test_the_step_of_a_checkpoint_is_read_without_inflating_it(tmp_path, monkeypatch) -> None:
    import torch

    plain = tmp_path / "mine.ckpt"
    torch.save({"global_step": 7, "state_dict": {"w": torch.zeros(4)}}, plain)
    assert checkpoint_step(plain) == 7
    deflated = deflated_torch_file({"global_step": 7, "pad": torch.zeros(2**16)}, tmp_path / "bomb.ckpt")
    read = []
    monkeypatch.setattr(torch, "load", lambda *a, **k: read.append(a))
    assert checkpoint_step(deflated) is None and not read  # refused from its zip directory: the step is unknown


def test_a_run_resumed_from_another_folders_checkpoint_does_not_replace_the_run_here(tmp_path) -> None:
    other, here = _finished_run(tmp_path / "A"), _finished_run(tmp_path / "R")
    ckpt = str(other / "checkpoints" / "last.ckpt")
    with pytest.raises(RunFolderError, match=rf"R already holds a run .*; {ckpt} is another run's checkpoint"):
        plan_folder(here, ckpt, ckpt, overwrite=False)
    assert plan_folder(here, ckpt, ckpt, overwrite=True) == [here / "checkpoints", here / "csv"]  # asked: replaced
    assert plan_folder(tmp_path / "new", ckpt, ckpt, overwrite=False) == []  # into a new folder: continued there


def test_overwrite_refuses_to_delete_files_a_run_does_not_write(tmp_path) -> None:
    here = _finished_run(tmp_path / "R")
    (here / "checkpoints" / ".last.ckpt.tmp-123").write_text("a killed run's temporary file: the run's")
    assert plan_folder(here, None, None, overwrite=True) == [here / "checkpoints", here / "csv"]
    (here / "checkpoints" / "my_best_backup.ckpt").write_text("mine")
    (here / "csv" / "my_analysis.txt").write_text("mine")
    with pytest.raises(
        RunFolderError,
        match=r"overwrite=true would delete checkpoints/my_best_backup\.ckpt, csv/my_analysis\.txt, which "
        r"unicorn-train did not write",
    ):
        plan_folder(here, None, None, overwrite=True)


def test_overwrite_replaces_the_evaluations_unicorn_eval_wrote_in_the_run(tmp_path) -> None:
    """``unicorn-eval`` writes ``<run>/eval/<dataset>_<split>/`` by default: the replaced run's, replaced with it;
    a folder of anything else there stays the user's."""
    here = _finished_run(tmp_path / "R")
    default = here / "eval" / "synthetic_test"
    (default / "report").mkdir(parents=True)
    for name in ("metrics.json", "metrics.csv", "per_image.csv", "report.html"):
        (default / name).write_text("an evaluation of the run's last.ckpt")
    assert here / "eval" in plan_folder(here, None, None, overwrite=True)
    (default / "notes.txt").write_text("mine")
    with pytest.raises(RunFolderError, match=r"would delete eval/synthetic_test, which unicorn-train did not write"):
        plan_folder(here, None, None, overwrite=True)


def test_overwrite_refuses_a_linked_output_folder(tmp_path) -> None:
    here, store = _finished_run(tmp_path / "R"), tmp_path / "store"
    (here / "checkpoints").rename(store)
    try:
        (here / "checkpoints").symlink_to(store)
    except (OSError, NotImplementedError):
        pytest.skip("symbolic links are not available here")
    with pytest.raises(RunFolderError, match=rf"overwrite=true: {here / 'checkpoints'} is a link to {store}"):
        plan_folder(here, None, None, overwrite=True)


def test_a_sweeps_folder_is_not_a_run_folder(tmp_path) -> None:
    (tmp_path / "multirun.yaml").write_text("hydra: {}")
    (tmp_path / "0").mkdir()
    for ckpt_arg, overwrite in ((None, False), ("last", False), (None, True)):
        with pytest.raises(RunFolderError, match=rf"^{tmp_path} is a sweep's folder \(multirun.yaml\): .* resume one"):
            plan_folder(tmp_path, ckpt_arg, None, overwrite=overwrite)


def test_a_sweep_does_not_replace_an_earlier_sweeps_record_unless_it_goes_on_with_it_or_replaces_it(tmp_path) -> None:
    plan_sweep_folder(tmp_path / "new", None, overwrite=False)  # no earlier sweep there
    plan_sweep_folder(tmp_path, None, overwrite=False)
    (tmp_path / "multirun.yaml").write_text("the earlier sweep's record")
    for ckpt_arg in (None, str(tmp_path / "other.ckpt")):  # a new sweep, from scratch or from a checkpoint
        with pytest.raises(
            RunFolderError, match=rf"^{tmp_path} holds an earlier sweep \(multirun.yaml, .*ckpt_path=last"
        ):
            plan_sweep_folder(tmp_path, ckpt_arg, overwrite=False)
    plan_sweep_folder(tmp_path, "last", overwrite=False)  # goes on with it
    plan_sweep_folder(tmp_path, None, overwrite=True)  # replaces it


def test_a_command_stopped_while_it_set_up_takes_back_only_its_empty_log_and_its_lock(tmp_path) -> None:
    made = tmp_path / "outputs" / "run"  # made by the command, with its parent
    made.mkdir(parents=True)
    (made / "train.log").touch()
    lock_folder(made)  # not released: the command stopped at once
    put_back_set_up(made, None, tmp_path / "outputs")
    assert list(tmp_path.iterdir()) == []
    # the user's folder: only the new empty log goes (its lock released), what it held before stays
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.log").write_text("")
    (mine / "train_ddp_process_1.log").write_text("an earlier run's")
    (mine / "train.log").touch()
    lock_folder(mine)
    put_back_set_up(mine, {"notes.log", "train_ddp_process_1.log"})
    assert sorted(p.name for p in mine.iterdir()) == ["notes.log", "train_ddp_process_1.log"]
    # a made folder holding more than an empty log (the run's log, a user's file) stays as it is
    (made / "train.log").parent.mkdir(parents=True)
    (made / "train.log").write_text("a line")
    (made / "notes.txt").write_text("mine")
    put_back_set_up(made, None, tmp_path / "outputs")
    assert sorted(p.name for p in made.iterdir()) == ["notes.txt", "train.log"]


def test_a_users_config_is_not_a_run(tmp_path) -> None:
    (tmp_path / "config.yaml").write_text("mine")
    for ckpt_arg in (None, "last"):  # not replaced by a resume either
        with pytest.raises(RunFolderError, match=r"holds config.yaml but no run; .*overwrite=true$"):
            plan_folder(tmp_path, ckpt_arg, None, overwrite=False)
    # unicorn-train's records of a run killed before its first checkpoint: ckpt_path=last trains it again
    (tmp_path / "provenance.json").write_text("[]")
    with pytest.raises(RunFolderError, match=r"but no run; .* \(a run killed before its first checkpoint: ckpt_path"):
        plan_folder(tmp_path, None, None, overwrite=False)
    assert plan_folder(tmp_path, "last", None, overwrite=False) == []


def test_a_locked_folder_refuses_a_second_lock_and_a_dead_owner_is_taken_over(tmp_path) -> None:
    lock = lock_folder(tmp_path / "run")
    assert (tmp_path / "run" / LOCK_NAME).read_text().split()[0] == str(os.getpid())
    with pytest.raises(RunFolderBusyError, match=rf"in use by another unicorn-train \(pid {os.getpid()} on "):
        lock_folder(tmp_path / "run")
    lock.release()
    assert not (tmp_path / "run" / LOCK_NAME).exists()
    (tmp_path / "run" / LOCK_NAME).write_text("999999999 elsewhere\n")  # left by a process that died
    lock_folder(tmp_path / "run").release()
    # a lock held by another process
    child = subprocess.Popen(
        [sys.executable, "-c", f"from unicorn.io.run_folder import lock_folder; import pathlib, sys, time; "
         f"lock_folder(pathlib.Path({str(tmp_path / 'run')!r})); print('locked', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert child.stdout.readline().strip() == "locked"
        with pytest.raises(RunFolderBusyError, match=rf"pid {child.pid} "):
            lock_folder(tmp_path / "run")
    finally:
        child.kill()
        child.wait()
    lock_folder(tmp_path / "run").release()  # the kernel released the killed owner's lock


def test_folder_changes_put_an_existing_folder_back(tmp_path) -> None:
    (tmp_path / "config.yaml").write_text("mine")
    (tmp_path / "train.log").write_text("old lines\n")
    (tmp_path / "notes").mkdir()
    changes = FolderChanges(tmp_path, {p.name for p in tmp_path.iterdir()})
    (tmp_path / "config.yaml").write_text("the run's")
    with open(tmp_path / "train.log", "a", encoding="utf-8") as f:
        f.write("new lines\n")
    (tmp_path / "csv").mkdir()
    (tmp_path / "csv" / "metrics.csv").write_text("x")
    changes.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yaml", "notes", "train.log"]
    assert (tmp_path / "config.yaml").read_text() == "mine" and (tmp_path / "train.log").read_text() == "old lines\n"
    created = tmp_path / "new"
    changes = FolderChanges(created, None)
    created.mkdir()
    (created / "train.log").write_text("x")
    changes.undo()
    assert not created.exists()


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None for p in sorted(folder.rglob("*"))}


def test_an_overwritten_run_is_back_when_the_new_one_fails_before_its_first_iteration(tmp_path) -> None:
    """``overwrite=true`` sets the earlier run's outputs aside; a run that stops before its first iteration puts them
    back, byte for byte (its records too), instead of leaving a folder whose records describe a deleted run."""
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"weights")
    (tmp_path / "csv").mkdir()
    (tmp_path / "csv" / "metrics.csv").write_text("step,loss\n0,1.0\n")
    (tmp_path / "diagnostics.csv").write_text("step\n30\n")
    (tmp_path / "config.yaml").write_text("the earlier run's")
    before = _snapshot(tmp_path)
    changes = FolderChanges(tmp_path, {p.name for p in tmp_path.iterdir()})
    outdated = plan_folder(tmp_path, None, None, overwrite=True)
    assert {p.name for p in outdated} == {"checkpoints", "csv", "diagnostics.csv"}
    aside = set_aside(outdated, tmp_path)
    assert aside is not None and not (tmp_path / "checkpoints").exists()
    (tmp_path / "config.yaml").write_text("the new run's")  # what the new run writes before training
    (tmp_path / "csv").mkdir()
    (tmp_path / "csv" / "hparams.yaml").write_text("new")
    changes.undo()
    assert _snapshot(tmp_path) == before


def test_folder_changes_remove_the_parents_the_run_created(tmp_path) -> None:
    top = tmp_path / "outputs"
    run = top / "train" / "runs" / "now"
    changes = FolderChanges(run, None, created_top=top)
    run.mkdir(parents=True)
    (run / "train.log").write_text("x")
    changes.undo()
    assert not top.exists() and tmp_path.is_dir()

    kept = tmp_path / "outputs" / "train" / "mine.txt"  # another process wrote beside the run: that stays
    changes = FolderChanges(run, None, created_top=top)
    run.mkdir(parents=True)
    kept.write_text("mine")
    changes.undo()
    assert not run.exists() and not run.parent.exists() and kept.read_text() == "mine"

    other = tmp_path / "elsewhere" / "run"  # a folder outside created_top: its parents are not the run's
    other.parent.mkdir()
    changes = FolderChanges(other, None, created_top=top)
    other.mkdir()
    changes.undo()
    assert not other.exists() and other.parent.is_dir()


def test_the_run_of_a_checkpoint_named_from_anywhere(tmp_path, monkeypatch) -> None:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    ckpt = run / "checkpoints" / "last.ckpt"
    ckpt.write_bytes(b"")
    (tmp_path / "elsewhere").mkdir()
    link = tmp_path / "elsewhere" / "best.ckpt"
    link.symlink_to(ckpt)
    assert run_of_checkpoint(ckpt) == run
    assert run_of_checkpoint(link) == run  # a link to the run's file
    monkeypatch.chdir(run / "checkpoints")
    assert run_of_checkpoint(Path("last.ckpt")) == run  # relative, from inside checkpoints/
    assert run_of_checkpoint("../checkpoints/last.ckpt") == run
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert run_of_checkpoint("best.ckpt") == run
    (tmp_path / "lone.ckpt").write_bytes(b"")
    assert run_of_checkpoint(tmp_path / "lone.ckpt") is None


def test_an_early_failure_removes_only_what_a_run_writes(tmp_path) -> None:
    """Files of the user's put into the folder while the run started stay, in an existing folder and a new one."""
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "notes.txt").write_text("mine")
    changes = FolderChanges(existing, {"notes.txt"})
    (existing / "config.yaml").write_text("the run's")
    (existing / "csv").mkdir()
    (existing / "csv" / "metrics.csv").write_text("step\n")
    (existing / "notes2.txt").write_text("mine too")  # while the data was generated
    (existing / "analysis").mkdir()
    (existing / "analysis" / "plot.py").write_text("mine too")
    changes.undo()
    assert sorted(p.name for p in existing.iterdir()) == ["analysis", "notes.txt", "notes2.txt"]
    assert (existing / "analysis" / "plot.py").read_text() == "mine too"

    new = tmp_path / "outputs" / "new"
    changes = FolderChanges(new, None, created_top=tmp_path / "outputs")
    new.mkdir(parents=True)
    (new / "train.log").write_text("started")
    (new / ".hydra").mkdir()
    (new / "notes.txt").write_text("mine")
    changes.undo()
    assert sorted(p.name for p in new.iterdir()) == ["notes.txt"]  # the folder stays for the user's file


def test_an_aside_left_by_another_process_is_never_taken_for_this_ones(tmp_path) -> None:
    """A run killed before its first iteration leaves its aside; a later process with the same pid (containers
    reuse pids) that fails early must neither put it back over the run's checkpoints nor delete them."""
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"the run's weights")
    stale = tmp_path / f".overwritten-{os.getpid()}"  # the name an aside had before it carried a token
    (stale / "checkpoints").mkdir(parents=True)
    (stale / "checkpoints" / "last.ckpt").write_bytes(b"an older run's")
    other = tmp_path / f".overwritten-{os.getpid()}-0badc0de"  # another process's, under this pid
    (other / "csv").mkdir(parents=True)
    before = _snapshot(tmp_path)
    changes = FolderChanges(tmp_path, {p.name for p in tmp_path.iterdir()})
    (tmp_path / "config.yaml").write_text("the refused run's")
    changes.undo()
    assert _snapshot(tmp_path) == before
    aside = set_aside([tmp_path / "checkpoints"], tmp_path)  # this process's own: a name of its own
    assert aside is not None and aside not in (stale, other) and aside.name.startswith(f".overwritten-{os.getpid()}-")
