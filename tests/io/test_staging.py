"""Output folders written to a temporary sibling: complete or as they were, also when a signal comes."""

from __future__ import annotations

import errno
import os
import signal
from pathlib import Path

import pytest

from unicorn.errors import Interrupted, interrupt_on_signal
from unicorn.io.staging import PARTIAL_MARK, OutputConflictError, check_writable, staged_folder


def _siblings(folder):
    return sorted(p.name for p in folder.parent.iterdir() if PARTIAL_MARK in p.name)


def test_a_new_folder_appears_only_complete(tmp_path) -> None:
    out = tmp_path / "out"
    with staged_folder(out) as staging:
        (staging / "a.txt").write_text("a")
        assert not out.exists()  # nothing visible while writing
    assert (out / "a.txt").read_text() == "a" and not _siblings(out)


def test_an_existing_folder_gets_the_new_files_and_keeps_the_others(tmp_path) -> None:
    out = tmp_path / "out"
    (out / "img").mkdir(parents=True)
    (out / "img" / "old.png").write_text("old")
    (out / "img" / "mesh.obj").write_text("old")
    (out / "notes.txt").write_text("mine")
    with staged_folder(out) as staging:
        (staging / "img").mkdir()
        (staging / "img" / "mesh.obj").write_text("new")
    assert (out / "img" / "mesh.obj").read_text() == "new"
    assert (out / "img" / "old.png").read_text() == "old" and (out / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("name", [".", "..", "sub/.."])
def test_the_current_or_parent_folder_is_written_into(tmp_path, monkeypatch, name) -> None:
    work = tmp_path / "work"
    (work / "sub").mkdir(parents=True)
    (work / "mine.txt").write_text("mine")
    monkeypatch.chdir(work)
    with staged_folder(name) as staging:
        (staging / "a.txt").write_text("a")
    out = (work / name).resolve()
    assert (out / "a.txt").read_text() == "a" and (work / "mine.txt").read_text() == "mine"
    assert not _siblings(out) and os.getcwd() == str(work)  # merged into the folder, which stays where it was


def test_the_root_folder_is_refused_in_one_line(tmp_path) -> None:
    with pytest.raises(OutputConflictError, match="choose a folder below it"):
        with staged_folder("/"):
            pass


@pytest.mark.parametrize("existing", [False, True])
def test_an_output_folder_on_another_file_system_gets_the_files(tmp_path, monkeypatch, existing) -> None:
    out = tmp_path / "out"
    if existing:
        (out / "img").mkdir(parents=True)
        (out / "img" / "mesh.obj").write_text("old")
        (out / "notes.txt").write_text("mine")
    rename = os.replace

    def across_devices(src, dst):  # a rename out of the staging folder crosses file systems, as into a mount point
        if any(part.startswith(f".out{PARTIAL_MARK}") and part[-1].isdigit() for part in Path(src).parts):
            raise OSError(errno.EXDEV, "Invalid cross-device link", str(src))
        rename(src, dst)

    monkeypatch.setattr(os, "replace", across_devices)
    with staged_folder(out) as staging:
        (staging / "img").mkdir()
        (staging / "img" / "mesh.obj").write_text("new")
        (staging / "img" / "more").mkdir()
        (staging / "img" / "more" / "a.png").write_text("a")
        (staging / "report.html").write_text("r")
    assert (out / "img" / "mesh.obj").read_text() == "new" and (out / "img" / "more" / "a.png").read_text() == "a"
    assert (out / "report.html").read_text() == "r"
    assert (out / "notes.txt").read_text() == "mine" if existing else not (out / "notes.txt").exists()
    leftovers = [p for p in tmp_path.rglob("*") if PARTIAL_MARK in p.name]
    assert leftovers == []  # neither the staging folder nor a copy stays


def test_a_failure_leaves_the_folder_as_it_was(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("before")
    with pytest.raises(ValueError), staged_folder(out) as staging:
        (staging / "a.txt").write_text("half")
        raise ValueError("bad image")
    assert [p.name for p in out.iterdir()] == ["a.txt"] and (out / "a.txt").read_text() == "before"
    assert not _siblings(out)
    with pytest.raises(ValueError), staged_folder(tmp_path / "new") as staging:
        raise ValueError("bad image")
    assert not (tmp_path / "new").exists() and not _siblings(tmp_path / "new")


def test_a_full_disk_names_the_folder(tmp_path) -> None:
    out = tmp_path / "out"
    with pytest.raises(OSError, match=rf"No space left on device while writing the output folder {out}"):
        with staged_folder(out):
            raise OSError(errno.ENOSPC, "No space left on device")  # as a write() on a full disk: no file name
    assert not out.exists()


def test_a_sibling_of_a_killed_process_is_removed(tmp_path) -> None:
    out = tmp_path / "out"
    dead = tmp_path / f".out{PARTIAL_MARK}999999999"
    dead.mkdir()
    live = tmp_path / f".out{PARTIAL_MARK}{os.getppid()}"
    live.mkdir()
    with staged_folder(out):
        pass
    assert not dead.exists() and live.exists()


def test_a_file_in_the_way_of_a_folder_leaves_the_folder_as_it_was(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old")
    (out / "b").write_text("a file of the user's, where a folder goes")
    (out / "c").mkdir()  # a folder of the user's, where a file goes
    (out / "c" / "keep.txt").write_text("mine")
    (tmp_path / "elsewhere").mkdir()
    (out / "d").symlink_to(tmp_path / "elsewhere")  # a link of the user's, where a folder goes
    said = {"b": "a file where a folder goes", "c": "a folder where a file goes", "d": "a link where a folder goes"}
    for clash, kind in said.items():
        with pytest.raises(OutputConflictError, match=rf"{out / clash} is {kind}; move it away"):
            with staged_folder(out) as staging:
                (staging / "a.txt").write_text("new")
                if clash == "c":
                    (staging / "c").write_text("a file")
                else:
                    (staging / clash).mkdir()
                    (staging / clash / "x.txt").write_text("new")
        assert (out / "a.txt").read_text() == "old"  # nothing moved
        assert (out / "b").read_text().startswith("a file of the user's")
        assert (out / "c" / "keep.txt").read_text() == "mine" and not _siblings(out)
        assert not any((tmp_path / "elsewhere").iterdir())


@pytest.mark.parametrize("existing", [False, True], ids=["new-folder", "existing-folder"])
def test_a_signal_while_the_files_move_stops_once_they_are_all_in_place(tmp_path, monkeypatch, existing) -> None:
    out = tmp_path / "out"
    if existing:
        (out / "img").mkdir(parents=True)
        (out / "img" / "a.txt").write_text("old")
    moved = []
    replace = os.replace

    def signalled_replace(src, dst):  # SIGTERM as the first entry moves
        if not moved:
            os.kill(os.getpid(), signal.SIGTERM)
        moved.append(os.path.basename(dst))
        replace(src, dst)

    monkeypatch.setattr(os, "replace", signalled_replace)
    with pytest.raises(Interrupted, match="stopped by SIGTERM"), interrupt_on_signal():
        with staged_folder(out) as staging:
            (staging / "img").mkdir()
            for name in ("a.txt", "b.txt", "c.txt"):
                (staging / "img" / name).write_text("new")
    assert moved == (["a.txt", "b.txt", "c.txt"] if existing else ["out"])
    assert {p.name: p.read_text() for p in (out / "img").iterdir()} == {n: "new" for n in ("a.txt", "b.txt", "c.txt")}
    assert not _siblings(out)


def test_the_commands_own_files_an_earlier_run_wrote_are_removed_from_the_folders_written_again(tmp_path) -> None:
    out = tmp_path / "out"
    for name in ("a", "b"):
        (out / name).mkdir(parents=True)
        for file in ("mesh.obj", "turntable.gif", "notes.txt"):
            (out / name / file).write_text("old")
    (out / "report.html").write_text("old")
    with staged_folder(out, outputs=("*/turntable.gif", "report.html", "*/mesh.obj")) as staging:
        (staging / "a").mkdir()
        (staging / "a" / "mesh.obj").write_text("new")  # no turntable this time
    assert (out / "a" / "mesh.obj").read_text() == "new" and not (out / "a" / "turntable.gif").exists()
    assert (out / "a" / "notes.txt").read_text() == "old"  # not the command's: kept
    # a folder this run did not write keeps all of its files; the top level, which every run writes, loses the
    # report this run did not make
    assert sorted(p.name for p in (out / "b").iterdir()) == ["mesh.obj", "notes.txt", "turntable.gif"]
    assert not (out / "report.html").exists()


def test_a_users_folder_named_like_one_of_the_commands_files_is_kept(tmp_path) -> None:
    """The commands' outputs are files: a folder that matches one of their patterns is the user's, and stays whole."""
    out = tmp_path / "out"
    (out / "a" / "turntable.gif").mkdir(parents=True)
    (out / "a" / "turntable.gif" / "frame.png").write_text("mine")
    (out / "report" / "sample01_mine").mkdir(parents=True)
    (out / "report" / "sample01_mine" / "notes.txt").write_text("mine")
    with staged_folder(out, outputs=("*/turntable.gif", "report/sample*")) as staging:
        (staging / "a").mkdir()
        (staging / "a" / "mesh.obj").write_text("new")  # no turntable this time, no report
    assert (out / "a" / "turntable.gif" / "frame.png").read_text() == "mine"
    assert (out / "report" / "sample01_mine" / "notes.txt").read_text() == "mine"


def test_a_folder_a_pattern_names_loses_the_commands_files_even_where_this_run_does_not_write_it(tmp_path) -> None:
    out = tmp_path / "out"
    for folder in ("report", "pictures"):
        (out / folder).mkdir(parents=True)
        for file in ("sample01_input.png", "sample02_input.png"):
            (out / folder / file).write_text("old")
    (out / "pictures" / "notes.txt").write_text("mine")
    with staged_folder(out, outputs=("report/sample*", "pictures/sample*")) as staging:
        (staging / "metrics.csv").write_text("new")  # no pictures this time
    # the earlier run's pictures go; a folder left empty goes with them, one holding a file of the user's stays
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["metrics.csv", "pictures", "pictures/notes.txt"]


def test_without_merge_a_folder_written_meanwhile_is_refused_and_left_as_it_is(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()  # empty: checked by the caller before the work began
    with pytest.raises(OutputConflictError, match=r"output folder .*out was written by another command"):
        with staged_folder(out, merge=False) as staging:
            (staging / "index.html").write_text("this run's")
            (out / "index.html").write_text("another run's")  # another process finished first
    assert [p.name for p in out.iterdir()] == ["index.html"] and (out / "index.html").read_text() == "another run's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary folder left
    (out / "index.html").unlink()
    with staged_folder(out, merge=False) as staging:  # still empty: written
        (staging / "index.html").write_text("this run's")
    assert (out / "index.html").read_text() == "this run's"


def _read_only(parent: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No temporary folder can be made in ``parent``, as in a read-only /mnt above a mount point."""
    real_mkdir = Path.mkdir

    def mkdir(self: Path, *args, **kwargs) -> None:
        if self.parent == parent and PARTIAL_MARK in self.name:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)


def test_an_existing_folder_whose_parent_cannot_be_written_holds_its_temporary_folder(tmp_path, monkeypatch) -> None:
    out = tmp_path / "mount"
    out.mkdir()
    (out / "mine.txt").write_text("kept")
    _read_only(tmp_path, monkeypatch)
    check_writable(out)
    with staged_folder(out) as staging:
        assert staging.parent == out
        (staging / "img").mkdir()
        (staging / "img" / "mesh.obj").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["img", "mine.txt"]
    assert (out / "img" / "mesh.obj").read_text() == "new"
    with pytest.raises(PermissionError, match=f"cannot write the output folder {tmp_path / 'new'}: Permission"):
        check_writable(tmp_path / "new")  # a folder to be made in the read-only parent


def test_without_merge_an_empty_folder_whose_parent_cannot_be_written_is_written(tmp_path, monkeypatch) -> None:
    out = tmp_path / "mount"
    out.mkdir()  # empty: the temporary folder inside it is this run's own, not another command's
    _read_only(tmp_path, monkeypatch)
    with staged_folder(out, merge=False) as staging:
        assert staging.parent == out
        (staging / "index.html").write_text("this run's")
    assert [p.name for p in out.iterdir()] == ["index.html"] and (out / "index.html").read_text() == "this run's"
    (out / "index.html").unlink()
    with pytest.raises(OutputConflictError, match=r"output folder .*mount was written by another command"):
        with staged_folder(out, merge=False) as staging:
            (staging / "index.html").write_text("this run's")
            (out / "index.html").write_text("another run's")
    assert [p.name for p in out.iterdir()] == ["index.html"] and (out / "index.html").read_text() == "another run's"


def test_a_read_only_output_folder_is_named_before_any_work(tmp_path, monkeypatch) -> None:
    out = tmp_path / "out"
    out.mkdir()

    def touch(self: Path, *args, **kwargs) -> None:
        raise OSError(errno.EROFS, "Read-only file system", str(self))

    monkeypatch.setattr(Path, "touch", touch)
    with pytest.raises(OSError, match=f"^\\[Errno 30\\] cannot write the output folder {out}: Read-only file system$"):
        check_writable(out)
    assert not list(out.iterdir()) and not _siblings(out)
