"""The model configuration's one definition: defaults from the dataclasses, ranges and choices checked once."""

from __future__ import annotations

import dataclasses

import pytest

from unicorn.config import ConfigError, validate
from unicorn.config.schema import StageDimsConfig
from unicorn.model import DEFAULT_CONFIG, Unicorn, UnicornConfig, check_model_config, merge_config, pose_objectives
from unicorn.model.compositing import list_compositings
from unicorn.model.config import (
    BRANCHES,
    CHOICES,
    CODE_BRANCHES,
    LossConfig,
    ShapeConfig,
    TextureConfig,
    allowed_values,
)
from unicorn.model.perceptual import list_perceptual_losses
from unicorn.model.pose_objectives import ExpectedLoss, list_pose_objectives


def test_merge_config_changes_only_the_named_keys_of_a_copy() -> None:
    merged = merge_config({"shape": {"code_dim": 16}}, loss={"rgb_weight": 2.0}, background=None)
    # the oracle: the dataclasses built with the same values, every other key at its declared default
    expected = UnicornConfig(shape=ShapeConfig(code_dim=16), loss=LossConfig(rgb_weight=2.0), background=None)
    assert merged == dataclasses.asdict(expected)
    assert merged["shape"]["n_field_units"] == ShapeConfig.n_field_units and merged["loss"]["rgb_weight"] == 2.0
    merged["texture"]["size"] = 7  # callers may edit what they get
    assert DEFAULT_CONFIG["texture"]["size"] == merge_config()["texture"]["size"] == TextureConfig.size != 7


def test_code_branches_are_the_branches_but_the_pose_and_the_stage_sizes() -> None:
    assert CODE_BRANCHES == ("shape", "texture", "background") and BRANCHES[-1] == "background"
    assert set(BRANCHES) - set(CODE_BRANCHES) == {"pose"}
    assert tuple(f.name for f in dataclasses.fields(StageDimsConfig)) == CODE_BRANCHES  # one size list per code


@pytest.mark.parametrize(
    ("groups", "message"),
    [
        ({"image_size": 4}, r"image_size must be >= 8, got 4"),
        ({"shape": {"code_dim": 0}}, r"shape\.code_dim must be >= 1, got 0"),
        ({"loss": {"min_angle": 200.0}}, r"loss\.min_angle must be in \[0, 180\], got 200"),
        ({"loss": {"perceptual": "lpips"}}, r"loss\.perceptual must be one of .*'lpips'"),
        ({"loss": {"pose_objective": "best"}}, r"loss\.pose_objective must be one of"),
        ({"renderer": {"composite": "over"}}, r"renderer\.composite must be one of"),
        ({"template": {"uv_mode": "flat"}}, r"template\.uv_mode must be one of"),
        ({"renderer": {"fov": None}}, r"exactly one of fov and focal_length"),
    ],
)
def test_bad_values_fail_naming_the_key(groups, message) -> None:
    with pytest.raises(ValueError, match=message):
        merge_config(groups)
    with pytest.raises(ValueError, match=message):
        Unicorn(groups)


def test_every_choice_names_a_string_setting() -> None:
    for key in CHOICES:
        group, name = key.split(".")
        assert DEFAULT_CONFIG[group][name] in allowed_values(key), key


def test_registered_constructors_are_the_allowed_values(monkeypatch) -> None:
    assert allowed_values("renderer.composite") == tuple(list_compositings())
    assert allowed_values("loss.perceptual") == (*list_perceptual_losses(), None)
    assert allowed_values("loss.pose_objective") == tuple(list_pose_objectives())
    # an objective registered by the user's code is accepted by the check with no list to update
    with pytest.raises(ValueError, match=r"loss\.pose_objective must be one of"):
        merge_config(loss={"pose_objective": "mine"})
    monkeypatch.setitem(pose_objectives._POSE_OBJECTIVES._factories, "mine", ExpectedLoss)
    assert merge_config(loss={"pose_objective": "mine"})["loss"]["pose_objective"] == "mine"


def test_background_none_skips_its_checks() -> None:
    cfg = merge_config(background=None)
    check_model_config(cfg)
    assert cfg["background"] is None


def test_training_config_uses_the_same_checks() -> None:
    # the same range and choice, reported under the training config's key
    base = {
        "model": {"image_size": 32},
        "dataset": {"img_size": 32, "root": None},
        "renderer": {"name": "layered", "camera": {"fov": 30.0}},
    }
    with pytest.raises(ConfigError, match=r"model\.shape\.code_dim must be >= 1"):
        validate({**base, "model": {"image_size": 32, "shape": {"code_dim": 0}}})
    with pytest.raises(ConfigError, match=r"model\.loss\.perceptual must be one of"):
        validate({**base, "model": {"image_size": 32, "loss": {"perceptual": "lpips"}}})
