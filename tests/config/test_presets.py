"""conf/'s presets as model configurations: model_preset reads them as unicorn-train composes them."""

from __future__ import annotations

from typing import Any

import pytest
from omegaconf import OmegaConf

from tests.support.training import compose_config
from unicorn.config import list_presets, model_config, model_preset, validate
from unicorn.config.schema import (
    CallbacksConfig,
    DatasetConfig,
    ModelConfig,
    PathsConfig,
    ScheduleConfig,
    TrainConfig,
    TrainerConfig,
)
from unicorn.model import DEFAULT_CONFIG, Unicorn
from unicorn.resources import config_dir


@pytest.mark.parametrize("family", list_presets("family"))
@pytest.mark.parametrize("size", list_presets("model"))
def test_model_preset_is_what_unicorn_train_composes(family: str, size: str, tmp_path, monkeypatch) -> None:
    # the oracle: a training run's composition of train.yaml with the model group and the family file
    monkeypatch.delenv("UNICORN_VGG16", raising=False)  # a preset names no weights file
    overrides = [f"model={size}", f"+family={family}", "dataset.img_size=64", f"paths.output_dir={tmp_path}"]
    expected = model_config(validate(compose_config(overrides)))
    assert model_preset(family, size) == expected


def test_model_preset_inside_a_hydra_application(tmp_path) -> None:
    """unicorn-train init_from=<released .pkl> reads a preset while Hydra runs: the application's Hydra is kept."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from unicorn.config.presets import _composed_preset

    (tmp_path / "app.yaml").write_text("answer: 42\n")
    with initialize_config_dir(config_dir=str(tmp_path), version_base="1.3"):
        running = GlobalHydra.instance().hydra
        _composed_preset.cache_clear()  # compose again
        assert model_preset("shapenet", "tiny")["template"]["level"] == 2
        assert GlobalHydra.instance().hydra is running and compose("app").answer == 42


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
        (("real", "small", "layerd"), ValueError, "no renderer preset or backend 'layerd'; presets: \\["),
    ],
)
def test_unknown_preset_names_fail_with_the_known_ones(args, error, message) -> None:
    with pytest.raises(error, match=message):
        model_preset(*args)


def test_unknown_override_key_fails() -> None:
    with pytest.raises(KeyError, match="code_size"):
        model_preset("real", "small", shape={"code_size": 3})


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(node, dict) or not node:
        return {prefix[:-1]: node}
    return {k: v for key, value in node.items() for k, v in _leaves(value, f"{prefix}{key}.").items()}


#: the schema node of each group whose presets are merged onto it, and the key that names a preset's choice
SCHEMA_OF_GROUP = {
    "model": (ModelConfig, "name"),
    "dataset": (DatasetConfig, "name"),
    "schedule": (ScheduleConfig, "mode"),
    "trainer": (TrainerConfig, None),
    "callbacks": (CallbacksConfig, None),
    "paths": (PathsConfig, None),
    "family": (TrainConfig, None),  # @package _global_
}


@pytest.mark.parametrize("group", sorted(SCHEMA_OF_GROUP))
def test_presets_hold_only_what_differs_from_the_schema(group: str) -> None:
    schema, name_key = SCHEMA_OF_GROUP[group]
    defaults = _leaves(OmegaConf.to_container(OmegaConf.structured(schema)))
    for preset in list_presets(group):
        values = _leaves(OmegaConf.to_container(OmegaConf.load(config_dir() / group / f"{preset}.yaml")))
        restated = [k for k, v in values.items() if k not in ("", name_key) and k in defaults and defaults[k] == v]
        assert not restated, f"conf/{group}/{preset}.yaml restates the schema's defaults of {restated}"


def test_every_renderer_preset_names_a_registered_renderer_and_its_file() -> None:
    from unicorn.render import list_renderers

    names = {p.stem: OmegaConf.load(p)["name"] for p in (config_dir() / "renderer").glob("*.yaml")}
    assert names and all(stem == name for stem, name in names.items()), names
    assert set(names) <= set(list_renderers())


def test_model_preset_takes_a_backend_without_a_preset_or_the_renderer_group() -> None:
    from unicorn.render import HardRenderer, register_renderer, unregister_renderer

    @register_renderer("probe_nearest")
    class Nearest(HardRenderer):
        pass

    try:
        cfg = model_preset("shapenet", "tiny", renderer="probe_nearest")
        assert cfg["renderer"]["name"] == "probe_nearest" and cfg["renderer"]["options"] == {}
        assert cfg["renderer"]["focal_length"] == model_preset("shapenet", "tiny")["renderer"]["focal_length"]
        group = model_preset("shapenet", "tiny", renderer={"name": "hard", "options": {"supersample": 2}})
        assert group["renderer"]["name"] == "hard" and group["renderer"]["options"] == {"supersample": 2}
    finally:
        unregister_renderer("probe_nearest")
    with pytest.raises(ValueError, match=r"^no renderer preset or backend 'probe_nearest'; presets: \["):
        model_preset("shapenet", "tiny", renderer="probe_nearest")
    with pytest.raises(TypeError, match=r"^renderer must be a preset's or a backend's name, or a mapping, got 3$"):
        model_preset("shapenet", "tiny", renderer=3)  # type: ignore[arg-type]
