"""``--device`` of ``unicorn-eval`` and ``unicorn-reconstruct``: a device this machine lacks (no CUDA, or a CUDA index
beyond its devices) is refused in one line, exit status 2, before any input is read or anything is written."""

from __future__ import annotations

import pytest
import torch

from unicorn.cli.errors import UsageError
from unicorn.cli.options import parse_device


def _command_line(command: str, tmp_path, device: str) -> list[str]:
    """A command line whose checkpoint and image do not exist: only the device is checked before them."""
    out = ["--out", str(tmp_path / "out"), "--device", device]
    return [str(tmp_path / "model.pt"), *([str(tmp_path / "photo.png")] if command == "reconstruct" else []), *out]


def _fake_gpus(monkeypatch, count: int) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: count > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: count)


@pytest.mark.parametrize("command", ["eval", "reconstruct"])
@pytest.mark.parametrize(
    "gpus, device, line",
    [
        (0, "cuda:7", "--device cuda:7: CUDA is not available on this machine; use --device cpu"),
        (0, "cuda", "--device cuda: CUDA is not available on this machine; use --device cpu"),
        (1, "cuda:7", "--device cuda:7: this machine has 1 CUDA device(s), cuda:0"),
        (2, "cuda:2", "--device cuda:2: this machine has 2 CUDA device(s), cuda:0 to cuda:1"),
    ],
)
def test_a_device_the_machine_lacks_is_one_line_before_anything_is_read(
    command, gpus, device, line, tmp_path, monkeypatch, capsys
):
    import importlib

    main = importlib.import_module(f"unicorn.cli.{command}").main
    _fake_gpus(monkeypatch, gpus)
    assert main(_command_line(command, tmp_path, device)) == 2
    assert capsys.readouterr().err == f"unicorn-{command}: error: {line}\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("device, index", [("cuda", None), ("cuda:0", 0), ("cuda:1", 1)])
def test_a_cuda_device_the_machine_has_is_taken(device, index, monkeypatch):
    _fake_gpus(monkeypatch, 2)
    assert parse_device(device) == torch.device("cuda", index)


def test_parse_device_refuses_an_index_beyond_the_devices(monkeypatch):
    _fake_gpus(monkeypatch, 1)
    with pytest.raises(UsageError, match=r"^--device cuda:1: this machine has 1 CUDA device\(s\), cuda:0$"):
        parse_device("cuda:1")
