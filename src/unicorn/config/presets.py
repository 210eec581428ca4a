"""The shipped presets (``conf/``) as model configurations, for code that builds a model without a training run.

``conf/`` is the only place presets live: ``conf/model/<size>.yaml`` (small, big, tiny), the dataset family's
``conf/family/<family>.yaml`` (real, shapenet) and ``conf/renderer/<renderer>.yaml``. :func:`model_preset` has
Hydra compose ``conf/train.yaml`` with ``model=<size> renderer=<renderer> +family=<family>`` (Hydra's own defaults
list and schema, as ``unicorn-train`` composes a run of that family's experiments) and returns the mapping
:class:`unicorn.model.Unicorn` takes.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from unicorn.config.build import model_config
from unicorn.model.config import merge_config
from unicorn.resources import config_dir

__all__ = ["list_presets", "model_preset"]


def list_presets(group: str) -> list[str]:
    """The preset names of a config group (``model``, ``family``, ``renderer``, ``experiment``, ...)."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


@contextmanager
def _shipped_configs() -> Iterator[None]:
    """Hydra's compose API on ``conf/``, also inside a running Hydra application (``unicorn-train init_from=`` a
    released model reads its preset), whose global state is put back afterwards."""
    running = GlobalHydra.instance().hydra
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            yield
    finally:
        if running is not None:
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(running)


@functools.cache
def _composed_preset(family: str, size: str, renderer: str) -> dict[str, Any]:
    """The model configuration Hydra composes for the three presets (read once per process)."""
    for group, name in (("family", family), ("model", size), ("renderer", renderer)):
        if name not in list_presets(group):
            raise ValueError(f"no {group} preset {name!r}; known: {list_presets(group)}")
    # paths.vgg16=null: a preset names no weights file (UNICORN_VGG16 is a training run's setting)
    overrides = [f"model={size}", f"renderer={renderer}", f"+family={family}", "paths.vgg16=null"]
    with _shipped_configs():
        cfg = compose("train", overrides=overrides)
    return model_config(cfg)


def model_preset(
    family: str = "real", size: str = "small", renderer: str | Mapping[str, Any] = "layered", **overrides: Any
) -> dict[str, Any]:
    """The model configuration of a dataset family (``real``, ``shapenet``) and a model size (``small``, ``big``,
    ``tiny``) as ``conf/`` defines them, with ``overrides`` (model config groups) merged on top.

    ``renderer`` is a renderer preset (``conf/renderer/<name>.yaml``); or the name of a backend registered without
    one (a plugin's: :func:`unicorn.render.list_renderers`), with its own default options; or a mapping of the
    ``renderer`` group's keys (``{"name": ..., "options": {...}}``) over the ``layered`` preset.

    Example:
        >>> cfg = model_preset("shapenet", "small", image_size=32)
        >>> cfg["background"] is None, cfg["renderer"]["focal_length"] is not None
        (True, True)

    Raises:
        ValueError: an unknown preset or backend name (the known ones are listed).
        TypeError: a ``renderer`` that is neither a name nor a mapping.
        KeyError: an unknown override group or key.
    """
    from unicorn.render import list_renderers

    if isinstance(renderer, Mapping):
        renderer, group = "layered", dict(renderer)
    elif not isinstance(renderer, str):
        raise TypeError(f"renderer must be a preset's or a backend's name, or a mapping, got {renderer!r}")
    elif renderer in list_presets("renderer"):
        group = {}
    elif renderer in list_renderers():  # a backend without a preset: its constructor's defaults
        renderer, group = "layered", {"name": renderer, "options": {}}
    else:
        raise ValueError(
            f"no renderer preset or backend {renderer!r}; presets: {list_presets('renderer')}, backends: "
            f"{list_renderers()}"
        )
    preset = copy.deepcopy(_composed_preset(family, size, renderer))
    if group:
        preset = merge_config(preset, renderer=group)
    return merge_config(preset, **overrides)
