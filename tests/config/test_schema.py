"""The schema as the base of conf/train.yaml: every key exists in a composed config, with its default."""

from __future__ import annotations

from dataclasses import asdict, fields
from typing import Any

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from tests.support.training import compose_config
from unicorn.config import validate
from unicorn.config.schema import SCHEMA_NAME, HeldOutConfig, ModelConfig, TrainConfig
from unicorn.resources import config_dir


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(node, dict) or not node:
        return {prefix[:-1]: node}
    return {k: v for key, value in node.items() for k, v in _leaves(value, f"{prefix}{key}.").items()}


def test_train_yaml_starts_from_the_schema() -> None:
    assert OmegaConf.load(config_dir() / "train.yaml").defaults[0] == SCHEMA_NAME


def test_every_key_exists_in_a_composed_config(tmp_path) -> None:
    # overrides like model.pose.n_azim=2 find every key, whatever the presets list
    composed = compose_config(["model=big", f"paths.output_dir={tmp_path}"])
    keys = set(_leaves(OmegaConf.to_container(composed.model)))
    assert keys == set(_leaves(asdict(ModelConfig()))) and composed.model.pose.n_azim == ModelConfig().pose.n_azim
    assert set(composed) == {f.name for f in fields(TrainConfig)}


def test_a_misspelt_key_fails_while_composing(tmp_path) -> None:
    with pytest.raises(ConfigCompositionException, match=r"model\.pose\.n_azimuth"):
        compose_config(["model.pose.n_azimuth=2", f"paths.output_dir={tmp_path}"])


def test_optional_groups_are_filled_from_the_command_line(tmp_path) -> None:
    # a mapping given to a group that is null (off) fills it, the rest of the group at its defaults
    out = f"paths.output_dir={tmp_path}"
    heldout = validate(compose_config(["callbacks.heldout={every_n_steps:5,max_images:4}", out])).callbacks.heldout
    assert (heldout.every_n_steps, heldout.max_images, heldout.split) == (5, 4, HeldOutConfig.split)
    shapenet = ["experiment=shapenet_chair", "model.background={n_reg_units:64}", out]
    background = validate(compose_config(shapenet)).model.background  # the family sets it to null
    assert background.n_reg_units == 64 and background.code_dim == ModelConfig().background.code_dim
    again = validate(compose_config(["callbacks.images=null", "callbacks.images={every_n_steps:4}", out]))
    assert again.callbacks.images.every_n_steps == 4 and again.callbacks.images.n_views == 4
