"""Checkpoint files: the restricted unpickler refuses code, the content hash catches corruption, writes are atomic."""

from __future__ import annotations

import collections
import errno
import io
import os
import pickle
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.support.checkpoints import deflated_torch_file, malicious
from unicorn.errors import UserError
from unicorn.io.serialization import (
    INTEGRITY_KEY,
    CheckpointError,
    CorruptCheckpointError,
    UnsafeCheckpointError,
    atomic_save,
    content_digest,
    link_into_place,
    load_checkpoint_file,
    remove_stale_temporaries,
    seal,
)
from unicorn.torch_files import TorchFileMemoryError, read_plain


def test_payload_is_refused_and_never_runs(tmp_path: Path) -> None:
    marker = tmp_path / "PWNED"
    path = malicious(tmp_path / "evil.pkl", marker)
    with pytest.raises(UnsafeCheckpointError) as info:
        load_checkpoint_file(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "--trust-checkpoint" in message
    assert "posix.system" in message or "os.system" in message  # names what the file wants to call
    assert isinstance(info.value, UserError) and isinstance(info.value, ValueError)
    assert not marker.exists()
    # the control: full unpickling (trust=True) does run it, so the test above could have failed
    load_checkpoint_file(path, trust=True)
    assert marker.exists()


def test_plain_data_and_old_numpy_values_load(tmp_path: Path) -> None:
    data = {
        "epoch": np.int64(7),
        "loss": np.float32(0.5),
        "mean": np.arange(6, dtype=np.float64).reshape(2, 3),
        "milestones": Counter({10: 1, 20: 1}),
        "kwargs": {"n_elev_azim": (1, 6), "name": "x", "ratio": 0.5, "flag": None},
        "state": {"w": torch.randn(3, 2)},
    }
    torch.save(data, tmp_path / "f.pt")
    out = load_checkpoint_file(tmp_path / "f.pt")
    assert out["epoch"] == 7 and out["milestones"] == Counter({10: 1, 20: 1})
    np.testing.assert_array_equal(out["mean"], data["mean"])
    assert torch.equal(out["state"]["w"], data["state"]["w"]) and out["kwargs"] == data["kwargs"]


def test_content_hash_catches_flipped_bytes(tmp_path: Path) -> None:
    path = atomic_save({"w": torch.arange(100_000, dtype=torch.float32), "meta": {"epoch": 3}}, tmp_path / "c.pt")
    assert INTEGRITY_KEY in torch.load(path, weights_only=True)
    assert set(load_checkpoint_file(path)) == {"w", "meta"}  # verified, key removed
    raw = bytearray(path.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 4096] = bytes(b ^ 0xFF for b in raw[middle : middle + 4096])
    path.write_bytes(bytes(raw))
    assert torch.load(path, weights_only=True)["meta"] == {"epoch": 3}  # torch itself reads it without complaint
    with pytest.raises(CorruptCheckpointError, match=f"checkpoint {path} is corrupted"):
        load_checkpoint_file(path)


def test_digest_follows_content() -> None:
    a = {"w": torch.ones(3), "n": 1, "l": [1.0, "x"]}
    same = {"w": torch.ones(3), "n": 1, "l": [1.0, "x"]}
    assert content_digest(a) == content_digest(same) == content_digest(seal(dict(a)))
    for other in ({**a, "n": 2}, {**a, "w": torch.ones(3, dtype=torch.float64)}, {**a, "w": torch.ones(1, 3)},
                  {**a, "l": [1.0, "y"]}, {**a, "w": torch.tensor([1.0, 1.0, 1.0 + 1e-7])}):  # fmt: skip
        assert content_digest(other) != content_digest(a)


def test_unreadable_file_is_one_error(tmp_path: Path) -> None:
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(CheckpointError, match="cannot read checkpoint"):
        load_checkpoint_file(tmp_path / "junk.pt")
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(CheckpointError, match="empty.ckpt: the file is empty$"):
        load_checkpoint_file(tmp_path / "empty.ckpt")
    # a plain pickle, an image, text: not torch files, with or without trust (torch's own message suggests
    # weights_only=False, which cannot read them either)
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1, 2, 3]))
    (tmp_path / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    (tmp_path / "notes.ckpt").write_text("epoch: 3\n")
    for name in ("list.pkl", "photo.png", "notes.ckpt"):
        for trust in (False, True):
            with pytest.raises(CheckpointError, match=f"{name}: it is not a file written by torch.save") as info:
                load_checkpoint_file(tmp_path / name, trust=trust)
            assert "weights_only" not in str(info.value)


@pytest.mark.parametrize(
    "error",
    [
        MemoryError(),
        RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate memory: you tried to "
                     "allocate 4294967296 bytes. Error code 12 (Cannot allocate memory)"),
        torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"),
    ],
    ids=["MemoryError", "cpu-allocator", "cuda"],
)  # fmt: skip
def test_running_out_of_memory_is_not_blamed_on_the_file(tmp_path: Path, monkeypatch, error: Exception) -> None:
    """A checkpoint or weights file that needs more memory than is free is one error naming the file and the memory,
    not a checkpoint that cannot be read."""
    path = tmp_path / "big.ckpt"
    torch.save({"w": torch.ones(3)}, path)

    def load(*args, **kwargs):
        raise raised

    raised = error
    monkeypatch.setattr(torch, "load", load)
    size = f"{path.stat().st_size:,}"
    for read in (load_checkpoint_file, read_plain):
        with pytest.raises(
            TorchFileMemoryError, match=rf"^ran out of memory loading \S+big.ckpt \({size} bytes\): "
        ) as info:
            read(path)
        assert isinstance(info.value, UserError) and isinstance(info.value, MemoryError)
        assert not isinstance(info.value, CheckpointError) and "\n" not in str(info.value)
    raised = RuntimeError("PytorchStreamReader failed reading zip archive: failed finding central directory")
    with pytest.raises(CheckpointError, match="cannot read checkpoint"):  # a damaged file is still the file's fault
        load_checkpoint_file(path)


@pytest.mark.parametrize("legacy", [False, True])
def test_both_torch_formats_are_read(tmp_path: Path, legacy: bool) -> None:
    path = tmp_path / "model.pt"
    torch.save({"w": torch.ones(2)}, path, _use_new_zipfile_serialization=not legacy)
    assert torch.equal(load_checkpoint_file(path)["w"], torch.ones(2))
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_checkpoint_file(tmp_path / "missing.pt")


@pytest.mark.parametrize("container", [dict, collections.OrderedDict], ids=["dict", "OrderedDict"])
def test_legacy_storages_declaring_more_than_the_file_are_refused(tmp_path: Path, monkeypatch, container) -> None:
    # the format before PyTorch 1.6 declares each storage's element count in its pickle, and torch.load allocates
    # that much before reading the bytes: 2**30 floats declared in a file of a few hundred bytes. A state dict of
    # that time (torchvision's VGG16 file) is an OrderedDict, whose items the pickle sets one by one
    buffer = io.BytesIO()
    saved = container(w=torch.ones(2), d=torch.ones(3, dtype=torch.float64))
    torch.save(saved, buffer, _use_new_zipfile_serialization=False)
    raw = buffer.getvalue()
    count = raw.index(b"K\x02N", raw.index(b"FloatStorage"))  # the float storage's count (BININT1 2), then no view
    crafted = tmp_path / "crafted.pt"
    crafted.write_bytes(raw[:count] + b"J" + (2**30).to_bytes(4, "little") + raw[count + 2 :])
    read = []
    monkeypatch.setattr(torch, "load", lambda *a, **k: read.append(a))
    for trust in (False, True):
        with pytest.raises(CheckpointError, match="crafted.pt: its tensors declare 4,294,967,320 bytes, more than"):
            load_checkpoint_file(crafted, trust=trust)
    assert not read  # refused before torch allocates anything
    monkeypatch.undo()
    (tmp_path / "saved.pt").write_bytes(raw)
    loaded = load_checkpoint_file(tmp_path / "saved.pt")
    assert torch.equal(loaded["w"], torch.ones(2)) and loaded["d"].dtype == torch.float64


def test_damaged_zip_is_one_line(tmp_path: Path) -> None:
    buffer = io.BytesIO()
    torch.save({"w": torch.ones(1000)}, buffer)
    (tmp_path / "half.pt").write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
    for trust in (False, True):
        with pytest.raises(CheckpointError, match="half.pt: it is a damaged zip archive, a truncated file") as info:
            load_checkpoint_file(tmp_path / "half.pt", trust=trust)
        assert "\n" not in str(info.value) and "PytorchStreamReader" not in str(info.value)


def _crafted_containers() -> list[tuple[str, object, str]]:
    """Values a pickle of a few hundred bytes can hold that no walk of them (the content hash, the config's
    conversion) finishes: shared lists repeating 2**21 items, a list holding itself, lists nested 150 deep."""
    shared: list = [0]
    for _ in range(21):
        shared = [shared, shared]
    loop: list = []
    loop.append(loop)
    deep: list = []
    for _ in range(150):
        deep = [deep]
    return [
        ("shared", shared, r"its shared containers repeat more than 1,000,000 items"),
        ("loop", loop, r"a list in it holds itself"),
        ("deep", deep, r"its containers nest more than 100 levels deep"),
    ]


@pytest.mark.parametrize("sealed", [False, True], ids=["plain", "sealed"])
def test_containers_no_walk_could_finish_are_refused(tmp_path: Path, sealed: bool) -> None:
    for name, value, message in _crafted_containers():
        data = {"state": {"w": torch.ones(2)}, "info": {"x": value}}
        if sealed:  # the hash is walked first
            data[INTEGRITY_KEY] = {"algorithm": "sha256", "digest": "0" * 64}
        path = tmp_path / f"{name}.pt"
        torch.save(data, path)
        assert path.stat().st_size < 4096
        with pytest.raises(CheckpointError, match=rf"cannot read checkpoint \S+{name}.pt: {message}") as info:
            load_checkpoint_file(path)
        assert "\n" not in str(info.value)
    # containers shared below the limit, as an honest file may share them, load
    rows = list(range(1000))
    torch.save({"info": {"x": [rows] * 900, "loop_free": [[rows]] * 3}}, tmp_path / "shared.pt")
    assert load_checkpoint_file(tmp_path / "shared.pt")["info"]["x"][899] == rows


def test_zip_entries_that_would_inflate_are_refused_from_the_directory(tmp_path: Path, monkeypatch) -> None:
    saved = tmp_path / "saved.pt"
    torch.save({"w": torch.zeros(2**16)}, saved)  # 256 KiB of zeros: deflated to a few hundred bytes
    deflated = deflated_torch_file({"w": torch.zeros(2**16)}, tmp_path / "deflated.pt")
    assert deflated.stat().st_size < saved.stat().st_size // 20
    # entries declaring more bytes than the file holds: overlapping entries, as torch.save never writes them
    overlapping = tmp_path / "overlapping.pt"
    raw = bytearray(saved.read_bytes())
    record = raw.index(b"PK\x01\x02", raw.index(b"PK\x01\x02") + 1)  # the second entry's directory record
    raw[record + 20 : record + 28] = (10 * len(raw)).to_bytes(4, "little") * 2  # its compressed and full size
    overlapping.write_bytes(raw)
    read = []
    monkeypatch.setattr(torch, "load", lambda *a, **k: read.append(a))
    for path, message in [
        (deflated, r"its entry '\S+' is compressed"),
        (overlapping, r"its entries declare [\d,]+ bytes"),
    ]:
        with pytest.raises(CheckpointError, match=rf"cannot read checkpoint \S+{path.name}: {message}") as info:
            load_checkpoint_file(path)
        assert "\n" not in str(info.value)
    assert not read  # refused before torch inflates anything
    monkeypatch.undo()
    assert torch.equal(load_checkpoint_file(saved)["w"], torch.zeros(2**16))


def test_stale_temporaries_are_removed(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    stale = tmp_path / f".last.ckpt.tmp-{dead_pid}"
    mine = tmp_path / f".step=4.ckpt.tmp-{os.getpid()}"
    live = tmp_path / f".last.ckpt.tmp-{os.getppid()}"  # another live process may be writing it
    for path in (stale, mine, live):
        path.write_bytes(b"partial")
    (tmp_path / "last.ckpt").write_bytes(b"x")
    assert sorted(remove_stale_temporaries(tmp_path)) == sorted([stale, mine])
    assert live.exists() and (tmp_path / "last.ckpt").exists()


def test_atomic_save_leaves_no_partial_file(tmp_path: Path, monkeypatch) -> None:
    path = atomic_save({"w": torch.zeros(3)}, tmp_path / "m.pt")

    def fail(*args):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        atomic_save({"w": torch.ones(3)}, path)
    assert torch.equal(load_checkpoint_file(path)["w"], torch.zeros(3))  # the earlier file is intact
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]


def test_atomic_save_on_a_full_disk_names_the_file(tmp_path: Path, monkeypatch) -> None:
    path = atomic_save({"w": torch.zeros(3)}, tmp_path / "m.pt")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")  # as the kernel reports it: no file named

    monkeypatch.setattr(os, "fsync", full)
    message = f"[Errno 28] No space left on device while writing {path} (the file there before, if any, is as it was)"
    with pytest.raises(OSError, match=f"^{re.escape(message)}$") as caught:
        atomic_save({"w": torch.ones(3)}, path)
    assert caught.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert torch.equal(load_checkpoint_file(path)["w"], torch.zeros(3))
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]


class _Unpicklable:
    def __reduce__(self):
        raise pickle.PicklingError("boom")


def test_atomic_save_keeps_the_previous_file(tmp_path):
    path = tmp_path / "last.ckpt"
    atomic_save({"step": 1}, path)
    with pytest.raises(pickle.PicklingError):
        atomic_save({"step": 2, "bad": _Unpicklable()}, path)
    assert load_checkpoint_file(path) == {"step": 1}  # sealed, and the seal matches
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


@pytest.mark.parametrize("links", [True, False], ids=["hard-link", "copy"])
def test_link_into_place_gives_a_complete_file_a_second_name(tmp_path, monkeypatch, links) -> None:
    source = atomic_save({"global_step": 3, "w": torch.arange(4.0)}, tmp_path / "step=0000003.ckpt")
    last = tmp_path / "last.ckpt"
    last.write_bytes(b"an earlier iteration's")
    if not links:  # a file system without hard links

        def no_links(*args):
            raise OSError(1, "Operation not permitted")

        monkeypatch.setattr(os, "link", no_links)
    assert link_into_place(source, last) == last
    assert last.read_bytes() == source.read_bytes() and last.samefile(source) == links
    assert load_checkpoint_file(last)["global_step"] == 3  # sealed, and verified as such
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt", "step=0000003.ckpt"]  # no temporary left
    source.unlink()  # the periodic file rotated away: last.ckpt keeps the bytes
    assert load_checkpoint_file(last)["global_step"] == 3
