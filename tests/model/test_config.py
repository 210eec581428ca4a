"""The model configuration's one definition: defaults from the dataclasses, ranges and choices checked once."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch

from unicorn.config import ConfigError, validate
from unicorn.config.schema import StageDimsConfig
from unicorn.model import DEFAULT_CONFIG, Unicorn, check_model_config, merge_config
from unicorn.model.config import BRANCHES, CHOICES, CODE_BRANCHES, ModelConfigError, allowed_values

#: every string setting of the model configuration with the values the library ships (docs/model.md, docs/renderer.md,
#: docs/training.md), written out here rather than read from the registries the check itself reads
DOCUMENTED_CHOICES = {
    "template.uv_mode": ("seamless", "reference"),
    "renderer.composite": ("direct", "reference"),
    "loss.uniform_reduction": ("sum", "mean"),
}


def test_merge_config_changes_only_the_named_keys_of_a_copy() -> None:
    defaults = copy.deepcopy(DEFAULT_CONFIG)
    assert defaults["shape"]["code_dim"] != 16 and defaults["loss"]["rgb_weight"] != 2.0  # the merge changes them
    merged = merge_config({"shape": {"code_dim": 16}}, loss={"rgb_weight": 2.0}, background=None)
    assert merged.keys() == defaults.keys() and merged["background"] is None
    changed = {
        (group, key): value
        for group, values in merged.items()
        if isinstance(values, dict)
        for key, value in values.items()
        if value != defaults[group][key]
    }
    assert changed == {("shape", "code_dim"): 16, ("loss", "rgb_weight"): 2.0}
    assert all(merged[group].keys() == defaults[group].keys() for group in merged if isinstance(merged[group], dict))
    merged["texture"]["size"] = 7  # callers may edit what they get: neither the defaults nor a later merge see it
    merged["loss"]["rgb_weight"] = 3.0
    assert DEFAULT_CONFIG == defaults and merge_config() == defaults


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


@pytest.mark.parametrize(
    ("groups", "message"),
    [
        # what a constructor refuses: the configuration's check names the key before any network is built
        ({"texture": {"size": 48}}, r"^texture\.size must be a power of 2, got 48$"),
        ({"image_size": 48}, r"^image_size must be a power of 2 \(the background model generates images"),
        ({"texture": {"active_dims": 200}}, r"^texture\.active_dims must be in \[0, texture\.code_dim=128\], got 200$"),
        ({"shape": {"code_dim": 4, "active_dims": 8}}, r"^shape\.active_dims must be in \[0, shape\.code_dim=4\]"),
        ({"background": {"active_dims": 129}}, r"^background\.active_dims must be in \[0, background\.code_dim=128\]"),
        (
            {"template": {"axes": (1.0, 0.0, 0.7)}},
            r"^template\.axes must be three finite numbers > 0 .*, got \[1\.0, 0\.0",
        ),
        ({"template": {"axes": (1.0, 0.7)}}, r"^template\.axes must be three finite numbers > 0"),
        (
            {"pose": {"T_range": (0.3, 0.3)}},
            r"^pose\.T_range must be a finite number or 3 of them .*, got \(0\.3, 0\.3\)$",
        ),
        ({"pose": {"T_range": -0.1}}, r"^pose\.T_range must be .* in \[0, inf\), got -0\.1$"),
        ({"pose": {"scale_range": 1.5}}, r"^pose\.scale_range must be .* in \[0, 1\) \(scales 1 \+- it"),
        ({"pose": {"prior_translation": (0.0, 0.0)}}, r"^pose\.prior_translation must be a finite number or 3"),
        (
            {"pose": {"prior_translation": (0.0, 0.0, 0.2)}},
            r"^pose\.prior_translation's z \(0\.2\) must exceed T_range's z",
        ),
        ({"loss": {"min_angle": 180.0}}, r"^loss\.min_angle must be below 180 .*, got 180\.0$"),
    ],
)
def test_what_the_networks_cannot_be_built_with_fails_naming_the_key(groups, message) -> None:
    with pytest.raises(ModelConfigError, match=message):
        merge_config(groups)
    with pytest.raises(ModelConfigError, match=message):
        Unicorn(groups)


@pytest.mark.parametrize(
    ("groups", "message"),
    [
        ({"image_size": 64.5}, r"^image_size must be a whole number >= 8, got 64\.5$"),
        ({"image_size": "64"}, r"^image_size must be a finite number >= 8, got '64'$"),
        ({"shape": {"code_dim": 31.5}}, r"^shape\.code_dim must be a whole number >= 1, got 31\.5$"),
        ({"encoder": {"width": 32.5}}, r"^encoder\.width must be a whole number >= 1, got 32\.5$"),
        ({"template": {"level": 2.5}}, r"^template\.level must be a whole number in \[0, 7\], got 2\.5$"),
        ({"encoder": {"shared": "false"}}, r"^encoder\.shared must be true or false, got 'false'$"),
        ({"shape": {"symmetric": 1}}, r"^shape\.symmetric must be true or false, got 1$"),
        ({"loss": {"viewpoint_azimuth_only": "no"}}, r"^loss\.viewpoint_azimuth_only must be true or false, got 'no'$"),
        ({"template": 3}, r"^model config group 'template' must be a mapping of its keys, got 3$"),
        ({"shape": [("code_dim", 8)]}, r"^model config group 'shape' must be a mapping of its keys, got \["),
        ({"template": {"level": 10**400}}, r"^template\.level must be in \[0, 7\], got 1000"),
    ],
)
def test_a_size_that_is_not_whole_or_a_switch_that_is_not_a_bool_is_named(groups, message) -> None:
    """Neither is rounded nor read as a truth value (64.5 is not 64, "false" is not on), a group is a mapping, a
    huge number is no size: each is named."""
    with pytest.raises(ModelConfigError, match=message):
        merge_config(groups)
    with pytest.raises(ModelConfigError, match=message):
        Unicorn(groups)


def test_whole_floats_are_sizes_the_networks_take() -> None:
    cfg = merge_config(image_size=32.0, shape={"code_dim": 16.0}, pose={"n_azim": 4.0}, background=None)
    assert (cfg["image_size"], cfg["shape"]["code_dim"], cfg["pose"]["n_azim"]) == (32, 16, 4)
    assert all(type(v) is int for v in (cfg["image_size"], cfg["shape"]["code_dim"], cfg["pose"]["n_azim"]))
    model = Unicorn(cfg)
    assert model.shape.code(torch.zeros(2, 512)).shape == (2, 16) and model.n_candidates == 4
    with pytest.raises(KeyError, match=r"^\"only the background model can be disabled \(None\), not 'image_size'\"$"):
        merge_config(image_size=None)


def test_sizes_the_networks_take_pass_the_check() -> None:
    # no background model: any image size (the ShapeNet family's renders), one number for a vector setting
    Unicorn(image_size=48, background=None, pose={"T_range": 0.1, "prior_translation": 2.0, "scale_range": 0.5})
    merge_config(texture={"size": 32.0, "active_dims": 128}, loss={"min_angle": 179.0})


def test_every_choice_names_a_string_setting() -> None:
    for key in CHOICES:
        group, name = key.split(".")
        assert DEFAULT_CONFIG[group][name] in allowed_values(key), key


@pytest.mark.parametrize(("key", "expected"), DOCUMENTED_CHOICES.items())
def test_allowed_values_are_the_documented_ones_and_each_is_accepted(key, expected) -> None:
    assert allowed_values(key) == expected
    group, name = key.split(".")
    for value in expected:
        assert merge_config({group: {name: value}})[group][name] == value


def test_every_string_setting_is_documented() -> None:
    assert set(CHOICES) == set(DOCUMENTED_CHOICES)


def test_background_none_skips_its_checks() -> None:
    cfg = merge_config(background=None)
    check_model_config(cfg)
    assert cfg["background"] is None


@pytest.mark.parametrize(
    "group, key, value, message",
    [
        ("pose", "azim_range", None, r"pose\.azim_range must be two finite numbers \[min, max\] .*, got None"),
        ("pose", "roll_range", 30, r"pose\.roll_range must be two finite numbers .*, got 30"),
        ("renderer", "background_color", None, r"renderer\.background_color must be three numbers .*, got None"),
        ("encoder", "pooled", None, r"encoder\.pooled must name distinct stages of .*, got None"),
        ("encoder", "pooled", 3, r"encoder\.pooled must name distinct stages of .*, got 3"),
        ("encoder", "pooled", [["layer4"]], r"encoder\.pooled must name distinct stages of .*, got \[\['layer4'\]\]"),
        ("encoder", "own", None, r"encoder\.own must be a list of branch names, got None"),
        ("encoder", "own", "texture", r"encoder\.own must be a list of branch names, got 'texture'"),
    ],
)
def test_a_list_setting_of_another_type_is_named(group, key, value, message) -> None:
    # a checkpoint's stored settings reach these checks untyped (a released .pkl's rend_predictor.azim_range: null)
    cfg = merge_config()
    cfg[group][key] = value
    with pytest.raises(ValueError, match=message):
        check_model_config(cfg)


@pytest.mark.parametrize(
    "groups, message",
    [
        # a second turn puts candidates on the azimuths of others
        ({"pose": {"azim_range": [0, 720]}}, r"^pose\.azim_range must span at most 360 degrees \(one turn\), got"),
        # nothing trains the pose or the shape from the images (the sampled objective failed on an empty stack)
        (
            {"loss": {"rgb_weight": 0, "perceptual_weight": 0}},
            r"^loss\.rgb_weight is 0 and there is no perceptual term .*: nothing would reconstruct the images$",
        ),
        ({"loss": {"rgb_weight": 0, "perceptual": None}}, r"^loss\.rgb_weight is 0 and there is no perceptual term"),
    ],
)
def test_a_config_that_cannot_train_is_named(groups, message) -> None:
    with pytest.raises(ModelConfigError, match=message):
        merge_config(groups)


def test_the_terms_and_ranges_that_can_train_pass() -> None:
    merge_config(pose={"azim_range": [-180, 180]}, loss={"rgb_weight": 0, "perceptual": "structural"})
    merge_config(loss={"perceptual_weight": 0})  # the pixel loss alone


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
