"""The model configuration's one definition: defaults from the dataclasses, ranges and choices checked once."""

from __future__ import annotations

import copy

import pytest

from unicorn.config import ConfigError, validate
from unicorn.model import DEFAULT_CONFIG, Unicorn, UnicornConfig, check_model_config, merge_config
from unicorn.model.config import CHOICES


def test_merge_config_changes_only_the_named_keys_of_a_copy() -> None:
    merged = merge_config({"shape": {"code_dim": 16}}, loss={"rgb_weight": 2.0}, background=None)
    expected = copy.deepcopy(DEFAULT_CONFIG)  # the oracle: the same edits made by hand
    expected["shape"]["code_dim"], expected["loss"]["rgb_weight"], expected["background"] = 16, 2.0, None
    assert merged == expected
    merged["texture"]["size"] = 7  # callers may edit what they get
    assert DEFAULT_CONFIG["texture"]["size"] == UnicornConfig().texture.size != 7


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
    for key, allowed in CHOICES.items():
        group, name = key.split(".")
        assert DEFAULT_CONFIG[group][name] in allowed, key


def test_background_none_skips_its_checks() -> None:
    cfg = merge_config(background=None)
    check_model_config(cfg)
    assert cfg["background"] is None


def test_training_config_uses_the_same_checks() -> None:
    # the same range and choice, reported under the training config's key
    base = {
        "model": {"image_size": 32},
        "dataset": {"img_size": 32},
        "renderer": {"name": "layered", "camera": {"fov": 30.0}},
    }
    with pytest.raises(ConfigError, match=r"model\.shape\.code_dim must be >= 1"):
        validate({**base, "model": {"image_size": 32, "shape": {"code_dim": 0}}})
    with pytest.raises(ConfigError, match=r"model\.loss\.perceptual must be one of"):
        validate({**base, "model": {"image_size": 32, "loss": {"perceptual": "lpips"}}})
