"""conf/'s presets as model configurations: model_preset reads them as unicorn-train composes them."""

from __future__ import annotations

from dataclasses import asdict

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from unicorn.config import list_presets, model_config, model_preset, validate
from unicorn.config.schema import ModelConfig
from unicorn.model import DEFAULT_CONFIG, Unicorn
from unicorn.resources import config_dir


def _composed(overrides: list[str]):
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return validate(compose("train", overrides=overrides))


@pytest.mark.parametrize("family", list_presets("family"))
@pytest.mark.parametrize("size", list_presets("model"))
def test_model_preset_is_what_unicorn_train_composes(family: str, size: str, tmp_path) -> None:
    # the oracle: Hydra's own composition of train.yaml with the model group and the family file
    overrides = [f"model={size}", f"+family={family}", "dataset.img_size=64", f"paths.output_dir={tmp_path}"]
    expected = model_config(_composed(overrides))
    assert model_preset(family, size) == expected


def test_small_real_preset_is_the_model_default() -> None:
    assert model_preset("real", "small") == DEFAULT_CONFIG


def test_shapenet_family_settings_reach_the_model() -> None:
    cfg = model_preset("shapenet", "big", image_size=32)
    assert cfg["image_size"] == 32 and cfg["background"] is None and not cfg["encoder"]["shared"]
    assert cfg["template"]["scale"] == 0.4 and cfg["renderer"]["fov"] is None
    assert cfg["renderer"]["options"]["faces_per_pixel"] == 50 and cfg["texture"]["code_dim"] == 512


def test_tiny_preset_builds_a_model() -> None:
    model = Unicorn(model_preset("shapenet", "tiny", image_size=32))
    assert model.template.num_verts == 162  # level 2


@pytest.mark.parametrize(
    ("args", "error", "message"),
    [
        (("nope", "small"), ValueError, "no family preset 'nope'"),
        (("real", "huge"), ValueError, "no model preset 'huge'"),
        (("real", "small", "layerd"), ValueError, "no renderer preset 'layerd'"),
    ],
)
def test_unknown_preset_names_fail_with_the_known_ones(args, error, message) -> None:
    with pytest.raises(error, match=message):
        model_preset(*args)


def test_unknown_override_key_fails() -> None:
    with pytest.raises(KeyError, match="code_size"):
        model_preset("real", "small", shape={"code_size": 3})


def _keys(node, prefix=""):
    out = set()
    for key, value in node.items():
        out |= _keys(value, f"{prefix}{key}.") if isinstance(value, dict) and key != "options" else {prefix + key}
    return out


def test_small_yaml_lists_every_model_key() -> None:
    # unicorn-train overrides like model.pose.n_azim=2 need the key in the composed config
    listed = OmegaConf.to_container(OmegaConf.load(config_dir() / "model" / "small.yaml"))
    assert _keys(listed) == _keys(asdict(ModelConfig()))


def test_every_renderer_preset_names_a_registered_renderer_and_its_file() -> None:
    from unicorn.render import list_renderers

    names = {p.stem: OmegaConf.load(p)["name"] for p in (config_dir() / "renderer").glob("*.yaml")}
    assert names and all(stem == name for stem, name in names.items()), names
    assert set(names) <= set(list_renderers())
