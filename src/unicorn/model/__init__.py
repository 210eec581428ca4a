"""UNICORN's structured autoencoder and its losses, as plain PyTorch modules.

- ``config``: the configuration's groups, defaults and checks (:class:`UnicornConfig`, :func:`merge_config`).
- :class:`Unicorn` (``autoencoder``): image -> shape, texture, pose, background -> rendered image (assembly,
  predict, render).
- ``objectives``: the two training steps (pose step, 3D step) and the neighbour loss, each returning its loss
  terms and the pose probabilities (:class:`StepLosses`); also :meth:`Unicorn.pose_step` / :meth:`Unicorn.step_3d`.
- Building blocks: ``template`` (ellipsoid mesh and UVs), ``encoder`` (ResNet-18), ``field`` (shape),
  ``generator`` (texture / background), ``pose`` (candidates and scale), ``progressive`` (code masks).
- Losses: ``losses`` (MSE, normal consistency, Laplacian, pose prior), ``perceptual`` (VGG16 / structural),
  ``neighbors`` (memory bank for the neighbour reconstruction).

Files in and out (released checkpoints, textured meshes) are :mod:`unicorn.io`'s.
"""

from unicorn.model.autoencoder import Prediction, Unicorn, count_parameters
from unicorn.model.config import DEFAULT_CONFIG, UnicornConfig, check_model_config, merge_config
from unicorn.model.encoder import ResNet18
from unicorn.model.field import DeformationField, ShapeHead
from unicorn.model.generator import CodeGenerator, GiraffeGenerator
from unicorn.model.losses import (
    NormalConsistencyLoss,
    UniformLaplacianLoss,
    candidate_assignment_loss,
    mse_per_sample,
    uniform_pose_prior,
)
from unicorn.model.mlp import MLP
from unicorn.model.neighbors import NeighborMatch, NeighborMemory
from unicorn.model.objectives import StepLosses
from unicorn.model.perceptual import StructuralLoss, VGGPerceptualLoss, load_vgg16_weights
from unicorn.model.pose import PoseHead, PoseOutput, ScaleHead
from unicorn.model.progressive import ProgressiveMask, active_dims_at
from unicorn.model.template import TemplateMesh

__all__ = [
    "DEFAULT_CONFIG",
    "MLP",
    "CodeGenerator",
    "DeformationField",
    "GiraffeGenerator",
    "NeighborMatch",
    "NeighborMemory",
    "NormalConsistencyLoss",
    "PoseHead",
    "PoseOutput",
    "Prediction",
    "ProgressiveMask",
    "ResNet18",
    "ScaleHead",
    "ShapeHead",
    "StepLosses",
    "StructuralLoss",
    "TemplateMesh",
    "Unicorn",
    "UnicornConfig",
    "UniformLaplacianLoss",
    "VGGPerceptualLoss",
    "active_dims_at",
    "candidate_assignment_loss",
    "check_model_config",
    "count_parameters",
    "load_vgg16_weights",
    "merge_config",
    "mse_per_sample",
    "uniform_pose_prior",
]

# README.md documents these three to users as ``unicorn.model.*``: kept as re-exports of their home in
# unicorn.io, imported on first use so that importing unicorn.model never imports unicorn.io (a higher floor).
_MOVED_TO_IO = {
    "load_reference_checkpoint": "unicorn.io.reference_checkpoints",
    "export_prediction": "unicorn.io.meshes",
    "save_mesh": "unicorn.io.meshes",
}


def __getattr__(name: str) -> object:
    if name in _MOVED_TO_IO:
        import importlib

        return getattr(importlib.import_module(_MOVED_TO_IO[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
