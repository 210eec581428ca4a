"""load_model on checkpoints whose content is malformed: every one is a one-line CheckpointError naming what is
wrong, raised before the model is built, never a traceback of the code that reads it."""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from tests.support.checkpoints import reference_state
from tests.support.evaluation import tiny_model
from unicorn.errors import UserError
from unicorn.io import CheckpointError, load_model
from unicorn.io.checkpoints import ModelTooLargeError


@pytest.fixture(scope="module")
def model() -> torch.nn.Module:
    return tiny_model("real", seed=1)


def _plain(model) -> dict:
    """What :func:`unicorn.io.save_model` writes, unsealed (as if edited by hand)."""
    state = {k: v.clone() for k, v in model.state_dict().items()}
    return {"format": "unicorn-model", "config": copy.deepcopy(model.config), "state_dict": state, "info": {}}


def _lightning(model) -> dict:
    """The keys of a ``unicorn-train`` ``.ckpt`` that :func:`load_model` reads."""
    state = {f"model.{k}": v.clone() for k, v in model.state_dict().items()}
    state.update(texture_average_p=torch.tensor(0.0), stage=torch.tensor(1))
    return {
        "epoch": 0,
        "global_step": 0,
        "state_dict": state,
        "hyper_parameters": {"model": copy.deepcopy(model.config)},
    }


def _reference() -> dict:
    return {"epoch": 5, "model_kwargs": {}, "model_state": reference_state()}


def _refused(data: dict, path: Path, message: str, error: type[Exception] = CheckpointError) -> None:
    """``data`` saved at ``path`` is refused by load_model with ``error``, one line matching ``message``."""
    torch.save(data, path)
    with pytest.raises(error, match=message) as info:
        load_model(path)
    assert isinstance(info.value, UserError) and "\n" not in str(info.value)


def _edit(data: dict, change: Callable[[dict], object]) -> dict:
    data = copy.deepcopy(data)
    change(data)
    return data


def test_weights_of_other_shapes_or_types_name_the_first_one(tmp_path: Path, model) -> None:
    key = "shape.regressor.0.weight"
    shape = list(model.state_dict()[key].shape)
    expected = re.escape(f"{key} [3, 3] in the file, {shape} in the model")
    plain = _plain(model)
    _refused(_edit(plain, lambda d: d["state_dict"].__setitem__(key, torch.zeros(3, 3))), tmp_path / "a.pt", expected)
    lightning = _edit(_lightning(model), lambda d: d["state_dict"].__setitem__(f"model.{key}", torch.zeros(3, 3)))
    _refused(lightning, tmp_path / "b.ckpt", expected)
    first = next(iter(plain["state_dict"]))
    _refused(
        _edit(plain, lambda d: d["state_dict"].__setitem__(first, 3)), tmp_path / "c.pt", f"{first} an int in the file"
    )
    # a released model: a tensor of another shape, a value that is not a tensor, a tensor its sizes are read from
    ref = _reference()
    bad = _edit(ref, lambda d: d["model_state"].__setitem__("scale_regressor.0.weight", torch.zeros(5, 5)))
    _refused(bad, tmp_path / "d.pkl", r"scale\.regressor\.0\.weight \[5, 5\] in the file, \[128, 512\] in the model")
    bad = _edit(ref, lambda d: d["model_state"].__setitem__("scale_regressor.0.bias", 1.5))
    _refused(bad, tmp_path / "e.pkl", r"model_state\['scale_regressor\.0\.bias'\] is a float, not a tensor")
    bad = _edit(ref, lambda d: d["model_state"].pop("txt_generator.regressor.0.weight"))
    _refused(bad, tmp_path / "f.pkl", r"missing key 'txt_generator\.regressor\.0\.weight'")


def test_model_settings_of_another_version_are_named(tmp_path: Path, model) -> None:
    message = r"its model settings are not ones this version of unicorn knows \(unknown key 'newopt'.*'shape'.*another"
    plain = _edit(_plain(model), lambda d: d["config"]["shape"].__setitem__("newopt", 3))
    _refused(plain, tmp_path / "a.pt", message)
    lightning = _edit(_lightning(model), lambda d: d["hyper_parameters"]["model"]["shape"].__setitem__("newopt", 3))
    _refused(lightning, tmp_path / "b.ckpt", message)
    _refused(_edit(_plain(model), lambda d: d["config"].__setitem__("newgroup", 1)), tmp_path / "c.pt", "'newgroup'")


def test_a_renderer_of_a_plugin_not_loaded_here_is_named_with_the_way_to_load_it(tmp_path: Path, model) -> None:
    message = r"unknown renderer 'nearest'; known: \[.*\]; a part registered by a plugin needs that plugin here too"
    _refused(
        _edit(_plain(model), lambda d: d["config"]["renderer"].__setitem__("name", "nearest")),
        tmp_path / "p.pt",
        message,
    )


@pytest.mark.parametrize(
    "group, key, message",
    [
        (None, "image_size", r"image_size=65536 needs 4,294,967,296 pixels .*UNICORN_MAX_IMAGE_PIXELS"),
        ("texture", "size", r"texture\.size=16384 needs 268,435,456 pixels .*UNICORN_MAX_IMAGE_PIXELS"),
    ],
)
def test_stored_image_and_texture_sizes_are_bounded_before_the_model_is_built(
    tmp_path: Path, model, monkeypatch, group: str | None, key: str, message: str
) -> None:
    from unicorn.model import Unicorn

    value = 65536 if key == "image_size" else 16384
    built = []
    monkeypatch.setattr(Unicorn, "__init__", lambda *a, **k: built.append(1))

    def huge(config: dict) -> None:
        (config if group is None else config[group])[key] = value

    _refused(_edit(_plain(model), lambda d: huge(d["config"])), tmp_path / "a.pt", message, ModelTooLargeError)
    lightning = _edit(_lightning(model), lambda d: huge(d["hyper_parameters"]["model"]))
    _refused(lightning, tmp_path / "b.ckpt", message, ModelTooLargeError)
    if key == "image_size":  # a released model's size comes from its model_kwargs
        reference = _edit(_reference(), lambda d: d["model_kwargs"].__setitem__("img_size", value))
        _refused(reference, tmp_path / "c.pkl", rf"released checkpoint \S+c\.pkl: {message}", ModelTooLargeError)
    assert not built


@pytest.mark.parametrize(
    "kind, change, message",
    [
        ("plain", lambda d: d.__setitem__("config", "hello"), r"its 'config' is a str, not a model config"),
        ("plain", lambda d: d.pop("config"), r"has no 'config'"),
        ("plain", lambda d: d.pop("state_dict"), r"has no 'state_dict'"),
        ("plain", lambda d: d.__setitem__("state_dict", [1]), r"its 'state_dict' is a list, not a dict of weights"),
        ("plain", lambda d: d.__setitem__("info", [1, 2]), r"its 'info' is a list, not a dict"),
        ("plain", lambda d: d.__setitem__("info", {"dataset": "xyz"}), r"its 'dataset' is a str, not a dict"),
        ("plain", lambda d: d.__setitem__("info", {"epoch": "abc"}), r"its 'epoch' is a str, not a whole number"),
        ("plain", lambda d: d["config"].__setitem__("image_size", "big"), r"'image_size'\] is a str, not a number"),
        ("plain", lambda d: d["config"].__setitem__("shape", 3), r"\['shape'\] is an int, not a dict"),
        (
            "lightning",
            lambda d: d["state_dict"].__setitem__("texture_average_p", torch.zeros(3)),
            r"its 'texture_average_p' is a tensor of shape \[3\], not a number",
        ),
        ("lightning", lambda d: d["state_dict"].__setitem__("stage", "x"), r"its 'stage' is a str, not a number"),
        ("lightning", lambda d: d["hyper_parameters"].__setitem__("model", "x"), r"'model' is a str, not a model"),
        ("lightning", lambda d: d.__setitem__("state_dict", [1]), r"its 'state_dict' is a list"),
        ("lightning", lambda d: d.__setitem__("global_step", 1.5), r"its 'global_step' is a float, not a whole"),
        (
            "reference",
            lambda d: d["model_kwargs"].__setitem__("rend_predictor", {"n_elev_azim": 6}),
            r"model_kwargs\['rend_predictor'\]\['n_elev_azim'\] = 6 is not two whole numbers",
        ),
        ("reference", lambda d: d.__setitem__("epoch", "x"), r"epoch = 'x' is not a whole number"),
        (
            "reference",
            lambda d: d["model_kwargs"].__setitem__("milestones", {"freeze_shape": "x"}),
            r"model_kwargs\['milestones'\]\['freeze_shape'\] = 'x' is not a finite number",
        ),
        ("reference", lambda d: d["model_kwargs"].__setitem__("mesh", "abc"), r"model_kwargs\['mesh'\] is a str"),
        ("reference", lambda d: d.__setitem__("model_kwargs", "abc"), r"model_kwargs is a str, not a dict"),
        ("reference", lambda d: d.__setitem__("model_state", "abc"), r"model_state is a str, not a dict of tensors"),
    ],
)
def test_malformed_fields_are_named(tmp_path: Path, model, kind: str, change, message: str) -> None:
    data = {"plain": _plain, "lightning": _lightning}.get(kind, lambda m: _reference())(model)
    _refused(_edit(data, change), tmp_path / "m.pt", message)
