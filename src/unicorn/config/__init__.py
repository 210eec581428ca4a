"""Training configuration: the structured schema of ``conf/``, its validation, and ``conf/``'s model presets.

Importing this package registers the schema's defaults in Hydra's ConfigStore (``train_schema``, the base of
``conf/train.yaml``) and initialises nothing of Hydra's; ``unicorn-train`` (:mod:`unicorn.cli.train`) is the Hydra
application.
"""

from unicorn.config.build import ConfigError, check_optim, model_config, renderer_settings, validate
from unicorn.config.presets import list_presets, model_preset
from unicorn.config.schema import TrainConfig

__all__ = [
    "ConfigError",
    "TrainConfig",
    "check_optim",
    "list_presets",
    "model_config",
    "model_preset",
    "renderer_settings",
    "validate",
]
