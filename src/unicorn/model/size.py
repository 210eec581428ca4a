"""The size of the model a configuration describes, counted and limited before the model is built."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from unicorn.checks import SizeLimitError, check_limit, env_limit
from unicorn.model.autoencoder import build_networks
from unicorn.model.config import merge_config

__all__ = ["MAX_MODEL_PARAMS", "MAX_MODEL_PARAMS_ENV", "check_model_size", "count_parameters"]


def count_parameters(config: Mapping[str, Any] | None = None, **groups: Any) -> int:
    """Parameters and buffers (elements) of the learned networks a configuration describes, counted without
    allocating them (built on the ``meta`` device): what a stored configuration would make
    :class:`unicorn.model.Unicorn` allocate, checked before building it (:func:`unicorn.io.load_model`).

    Raises:
        KeyError, ValueError: as :func:`unicorn.model.config.merge_config`.
    """
    cfg = merge_config(config, **groups)
    with torch.device("meta"):
        networks = [m for m in build_networks(cfg).values() if m is not None]
    return sum(t.numel() for m in networks for t in [*m.parameters(), *m.buffers()])


#: the largest model (parameters and buffers of its networks) a stored or composed configuration may build: ten
#: times the paper's big model (49 M); ``$UNICORN_MAX_MODEL_PARAMS`` sets another limit (0: none). A checkpoint of a
#: few MB can describe a model of hundreds of GB.
MAX_MODEL_PARAMS = 500_000_000
#: the environment variable that sets another limit
MAX_MODEL_PARAMS_ENV = "UNICORN_MAX_MODEL_PARAMS"


def check_model_size(
    config: Mapping[str, Any], setting: str, limit: int | None = None, error: type[SizeLimitError] = SizeLimitError
) -> None:
    """Refuse a model configuration whose networks exceed ``limit`` elements, before allocating them.

    Args:
        config: a merged model configuration.
        setting: what asks for the model, named in the message (``"checkpoint PATH"``, ``"model"``).
        limit: the most parameters and buffers; None: ``$UNICORN_MAX_MODEL_PARAMS`` or :data:`MAX_MODEL_PARAMS`;
            0: no limit.
        error: the class raised (a subclass of :class:`~unicorn.checks.SizeLimitError`).

    Raises:
        SizeLimitError: the model is larger (:func:`unicorn.checks.check_limit`).
    """
    if limit is None:
        limit = env_limit(MAX_MODEL_PARAMS_ENV, MAX_MODEL_PARAMS, "parameters") or 0
    if limit <= 0:
        return
    n = count_parameters(config)
    what = f"its networks, {4 * n / 2**30:.1f} GiB as float32, at encoder.width={config['encoder']['width']}"
    check_limit(setting, what, n, limit, "parameters", f"{MAX_MODEL_PARAMS_ENV}; 0: no limit", error)
