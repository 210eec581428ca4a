"""``RenderSettings``: the renderer options' defaults and ranges are defined once and every path checks them."""

from __future__ import annotations

import dataclasses
import inspect

import pytest
import torch

from unicorn.config import ConfigError
from unicorn.config.build import renderer_settings
from unicorn.model.config import DEFAULT_CONFIG, RendererConfig
from unicorn.render import (
    BACKGROUND_COLOR,
    DEFAULT_SETTINGS,
    LayeredRasterizer,
    LayeredRenderer,
    MeshRasterizer,
    MeshRenderer,
    RenderError,
    RenderSettings,
    TexturesVertex,
    build_renderer,
    get_renderer_class,
    list_renderers,
)


def _defaults(cls: type) -> dict[str, object]:
    params = inspect.signature(cls).parameters.values()
    return {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}


@pytest.mark.parametrize("name", ["layered", "softras", "hard"])
def test_the_backends_take_their_defaults_from_the_settings(name: str) -> None:
    defaults = _defaults(get_renderer_class(name))
    shared = {f.name for f in dataclasses.fields(RenderSettings)} & set(defaults)
    assert {"background_color", "max_candidates", "perspective_correct"} <= shared
    own = {"faces_per_pixel": 50} if name == "softras" else {}  # SoftRas keeps more faces: nothing is hidden
    assert {k: defaults[k] for k in shared} == {k: own.get(k, getattr(DEFAULT_SETTINGS, k)) for k in shared}
    settings = build_renderer(name, image_size=(8, 12), background_color=[0, 0.5, 1]).settings
    assert settings.image_size == (8, 12) and settings.background_color == (0.0, 0.5, 1.0)


def test_the_background_colour_has_one_default() -> None:
    assert BACKGROUND_COLOR == (1.0, 1.0, 1.0) == DEFAULT_SETTINGS.background_color
    assert _defaults(MeshRenderer)["background_color"] is BACKGROUND_COLOR
    assert RendererConfig().background_color is BACKGROUND_COLOR
    without = renderer_settings({"name": "layered", "camera": {"fov": 30.0}})
    assert without["background_color"] == BACKGROUND_COLOR
    assert DEFAULT_CONFIG["renderer"]["options"] == {"sigma": 1e-4, "faces_per_pixel": 25, "perspective_correct": False}


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("faces_per_pixel", 0, "faces_per_pixel must be a whole number >= 1, got 0"),
        ("faces_per_pixel", 2.5, "faces_per_pixel must be a whole number >= 1, got 2.5"),
        ("supersample", 0.5, "supersample must be a whole number >= 1, got 0.5"),
        ("supersample", 1.5, "supersample must be a whole number >= 1, got 1.5"),
        ("sigma", float("nan"), "sigma must be a finite number >= 0, got nan"),
        ("gamma", -1.0, "gamma must be a finite number > 0, got -1.0"),
        ("gamma", 0.0, "gamma must be a finite number > 0, got 0.0"),
        ("eps", "small", "eps must be a finite number >= 0, got 'small'"),
        ("max_candidates", True, "max_candidates must be a whole number >= 1, got True"),
        ("max_bytes", -1, "max_bytes must be a whole number >= 0, got -1"),
        ("max_bytes", float("nan"), "max_bytes must be a whole number >= 0, got nan"),
        ("perspective_correct", "yes", "perspective_correct must be True or False, got 'yes'"),
        ("background_color", (1.0, float("inf")), r"background_color must be one finite number per channel"),
        ("background_color", "white", r"background_color must be one finite number per channel"),
    ],
)
def test_each_range_is_checked_by_the_settings_and_the_training_config(option: str, value, message: str) -> None:
    with pytest.raises(RenderError, match=f"^{message}"):
        RenderSettings(**{option: value})
    if option != "background_color":  # the model's own check names it (RGB in [0, 1])
        name = "hard" if option == "supersample" else "softras"
        with pytest.raises(ConfigError, match=f"^renderer.{message}"):
            renderer_settings({"name": name, "camera": {"fov": 30.0}, option: value})
    if option in ("faces_per_pixel", "supersample", "max_candidates", "max_bytes", "perspective_correct"):
        with pytest.raises(RenderError, match=f"^{message}"):
            MeshRasterizer(**{option: value})


def test_the_layered_renderer_keeps_its_earlier_name() -> None:
    assert LayeredRasterizer is LayeredRenderer is get_renderer_class("layered")
    assert "layered" in list_renderers()


def _background(renderer: MeshRenderer) -> torch.Tensor:
    """(C,) the colour ``renderer`` puts where no face is: an empty mesh's render."""
    images = renderer(torch.zeros(1, 0, 3), torch.zeros(0, 3, dtype=torch.long), TexturesVertex(torch.zeros(1, 0, 3)))
    return images[0, :3, 0, 0]


@pytest.mark.parametrize("name", ["layered", "softras", "hard"])
def test_the_settings_report_the_background_colour_the_renderer_renders(name: str) -> None:
    renderer = build_renderer(name, image_size=4, background_color=(0.1, 0.2, 0.3))
    assert renderer.settings.background_color == (0.1, 0.2, 0.3)  # as given, not rounded to float32
    renderer.load_state_dict(build_renderer(name, image_size=4, background_color=(0.0, 0.25, 1.0)).state_dict())
    assert renderer.settings.background_color == (0.0, 0.25, 1.0)
    assert torch.equal(_background(renderer), torch.tensor([0.0, 0.25, 1.0]))
    rebuilt = build_renderer(name, image_size=4, background_color=renderer.settings.background_color)
    assert torch.equal(_background(rebuilt), _background(renderer))
    with torch.no_grad():  # the buffer is the one record of the colour, whatever changes it
        renderer.background_color.fill_(0.5)
    assert renderer.settings.background_color == (0.5, 0.5, 0.5)
    assert renderer.settings.image_size == (4, 4)  # the other settings as given
