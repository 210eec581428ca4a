"""Training configuration: the structured schema of ``conf/`` and its validation.

Importing this package does not touch Hydra's global state; ``unicorn-train`` (:mod:`unicorn.cli.train`) is
the Hydra application.
"""

from unicorn.config.build import ConfigError, model_config, renderer_settings, validate
from unicorn.config.schema import TrainConfig

__all__ = ["ConfigError", "TrainConfig", "model_config", "renderer_settings", "validate"]
