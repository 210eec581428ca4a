"""UNICORN's structured autoencoder and its losses, as plain PyTorch modules.

- :class:`Unicorn` (``autoencoder``): image -> shape, texture, pose, background -> rendered image, with the
  two training steps :meth:`Unicorn.pose_step` and :meth:`Unicorn.step_3d`.
- Building blocks: ``template`` (ellipsoid mesh and UVs), ``encoder`` (ResNet-18), ``field`` (shape),
  ``generator`` (texture / background), ``pose`` (candidates and scale), ``progressive`` (code masks).
- Losses: ``losses`` (MSE, normal consistency, Laplacian, pose prior), ``perceptual`` (VGG16 / structural),
  ``neighbors`` (memory bank for the neighbour reconstruction).
- ``checkpoint_compat`` (released checkpoints) and ``export`` (textured meshes).
"""

from unicorn.model.autoencoder import DEFAULT_CONFIG, Prediction, Unicorn, merge_config, unicorn_config
from unicorn.model.checkpoint_compat import (
    config_from_reference,
    convert_reference_state_dict,
    load_reference_checkpoint,
)
from unicorn.model.encoder import ResNet18
from unicorn.model.export import export_prediction, save_mesh, textured_mesh
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
    "StructuralLoss",
    "TemplateMesh",
    "Unicorn",
    "UniformLaplacianLoss",
    "VGGPerceptualLoss",
    "active_dims_at",
    "candidate_assignment_loss",
    "config_from_reference",
    "convert_reference_state_dict",
    "export_prediction",
    "load_reference_checkpoint",
    "load_vgg16_weights",
    "merge_config",
    "mse_per_sample",
    "save_mesh",
    "textured_mesh",
    "uniform_pose_prior",
    "unicorn_config",
]
