"""The shipped presets (``conf/``) as model configurations, for code that builds a model without a training run.

``conf/`` is the only place presets live: ``conf/model/<size>.yaml`` (small, big, tiny), the dataset family's
``conf/family/<family>.yaml`` (real, shapenet) and ``conf/renderer/<renderer>.yaml``. :func:`model_preset` reads
those three files the way ``unicorn-train model=<size> renderer=<renderer>`` with a family's experiment composes
them (tests check that the two agree) and returns the mapping :class:`unicorn.model.Unicorn` takes.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from unicorn.config.build import model_config
from unicorn.config.schema import TrainConfig
from unicorn.model.config import merge_config
from unicorn.resources import config_dir

__all__ = ["list_presets", "model_preset"]


def list_presets(group: str) -> list[str]:
    """The preset names of a config group (``model``, ``family``, ``renderer``, ``experiment``, ...)."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


def _group_file(group: str, name: str) -> DictConfig:
    """``conf/<group>/<name>.yaml`` with its defaults list applied (entries of the same group and ``_self_``)."""
    if name not in list_presets(group):
        raise ValueError(f"no {group} preset {name!r}; known: {list_presets(group)}")
    node = OmegaConf.load(config_dir() / group / f"{name}.yaml")
    assert isinstance(node, DictConfig)
    defaults = list(node.pop("defaults", None) or [])
    if defaults and "_self_" not in defaults:
        raise ValueError(f"conf/{group}/{name}.yaml: a defaults list needs _self_ (Hydra's order is then explicit)")
    parts = [node if entry == "_self_" else _group_file(group, str(entry)) for entry in defaults] or [node]
    merged = OmegaConf.merge(*parts)
    assert isinstance(merged, DictConfig)
    return merged


def model_preset(
    family: str = "real", size: str = "small", renderer: str = "layered", **overrides: Any
) -> dict[str, Any]:
    """The model configuration of a dataset family (``real``, ``shapenet``) and a model size (``small``, ``big``,
    ``tiny``) as ``conf/`` defines them, with ``overrides`` (model config groups) merged on top.

    Example:
        >>> cfg = model_preset("shapenet", "small", image_size=32)
        >>> cfg["background"] is None, cfg["renderer"]["focal_length"] is not None
        (True, True)

    Raises:
        ValueError: an unknown preset name (the known ones are listed).
        KeyError: an unknown override group or key.
    """
    family_node = _group_file("family", family)
    cfg = OmegaConf.merge(
        OmegaConf.structured(TrainConfig),
        {"model": _group_file("model", size), "renderer": _group_file("renderer", renderer)},
        {"model": family_node.get("model", {}), "renderer": family_node.get("renderer", {})},
    )
    assert isinstance(cfg, DictConfig)
    return merge_config(model_config(cfg), **overrides)
