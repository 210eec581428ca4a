"""The trainer flags ``validate`` refuses because the run could not train with them: more than one device with a
strategy that is Lightning's plain DDP (the pose / 3D alternation leaves parameters without gradient at every step),
an accelerator whose package is missing. Each is one ``ConfigError`` line naming the setting and what to use."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from tests.support.training import compose_config
from unicorn.config import ConfigError, validate

SYNTHETIC = ["experiment=synthetic"]
FIND_UNUSED = r"use trainer\.strategy=ddp_find_unused_parameters_true \(as trainer=ddp and trainer=ddp_cpu do\)"


def _validate(tmp_path, *overrides: str):
    return validate(compose_config([*SYNTHETIC, *overrides, f"paths.output_dir={tmp_path}"]))


@pytest.mark.parametrize(
    "overrides, named",
    [
        (["trainer.accelerator=cpu", "trainer.devices=2"], r"trainer\.devices=2 "),
        (["trainer.accelerator=cpu", "trainer.devices='2'"], r"trainer\.devices=2 "),
        (["trainer=cpu", "trainer.devices=3"], r"trainer\.devices=3 "),
        (["trainer.accelerator=cpu", "trainer.num_nodes=2"], r"trainer\.num_nodes=2 "),
    ],
)
def test_more_than_one_device_with_strategy_auto_is_refused(tmp_path, overrides, named) -> None:
    with pytest.raises(ConfigError, match=rf"^trainer\.strategy=auto with {named}.*plain DDP.*{FIND_UNUSED}") as info:
        _validate(tmp_path, *overrides)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "overrides, named",
    [
        (["trainer=default"], r"trainer\.devices=auto \(4 devices on this machine\)"),
        (["trainer.accelerator=gpu", "trainer.devices=-1"], r"trainer\.devices=-1 \(4 devices on this machine\)"),
        (["trainer.accelerator=cuda", "trainer.devices=[0,1]"], r"trainer\.devices=\[0, 1\] "),
    ],
)
def test_every_gpu_of_a_machine_with_several_is_refused_with_strategy_auto(
    tmp_path, monkeypatch, overrides, named
) -> None:
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)  # what Lightning counts the GPUs with
    with pytest.raises(ConfigError, match=rf"^trainer\.strategy=auto with {named}.*{FIND_UNUSED}"):
        _validate(tmp_path, *overrides)


@pytest.mark.parametrize(
    "overrides",
    [
        [],  # the experiment's trainer=cpu: one CPU
        ["trainer=default"],  # every device of a machine without GPUs: one CPU
        ["trainer=ddp_cpu"],
        ["trainer.accelerator=cpu", "trainer.devices=2", "trainer.strategy=ddp_find_unused_parameters_true"],
        ["trainer.accelerator=cpu", "trainer.devices=1"],
    ],
)
def test_one_device_or_ddp_with_unused_parameters_passes(tmp_path, monkeypatch, overrides) -> None:
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)  # on any machine: no GPU
    _validate(tmp_path, *overrides)


def test_one_gpu_of_several_passes(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)
    assert _validate(tmp_path, "trainer=gpu").trainer.devices == 1


@pytest.mark.skipif(importlib.util.find_spec("torch_xla") is not None, reason="torch_xla is installed")
def test_an_accelerator_whose_package_is_missing_is_named(tmp_path) -> None:
    with pytest.raises(ConfigError) as info:
        _validate(tmp_path, "trainer.accelerator=tpu")
    message = str(info.value)
    assert message.startswith("trainer.accelerator=tpu needs a package that is not installed: ")
    assert "torch_xla" in message and "\n" not in message
