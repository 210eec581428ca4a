"""UNICORN's structured autoencoder and its building blocks, as plain PyTorch modules: it predicts and renders.

- ``config``: the configuration's groups, defaults and checks (:class:`UnicornConfig`, :func:`merge_config`).
- ``ranges``: dataclass fields declared with their range (``ranged``) and checked once (``check_ranges``).
- :class:`Unicorn` (``autoencoder``): image -> shape, texture, pose, background -> rendered image (assembly,
  predict, render); typed predictions (:class:`Prediction`, :class:`Prediction3D`). It holds no training state:
  the training objectives (pose step, 3D step, neighbour loss and memory) are :mod:`unicorn.objectives`'.
- ``compile``: ``torch.compile`` of the networks, with a fallback that says why (:func:`compile_networks`).
- Building blocks: ``template`` (ellipsoid mesh and UVs), ``encoder`` (ResNet-18), ``field`` (shape),
  ``generator`` (texture / background), ``pose`` (candidates and scale), ``progressive`` (code masks),
  ``compositing`` (how the object is put over its background, by name: :func:`build_compositing`).

The loss functions, the pose objectives and test-time refinement are the training floor's
(:mod:`unicorn.objectives`).

Files in and out (released checkpoints, textured meshes) are :mod:`unicorn.io`'s.
"""

from unicorn.model.autoencoder import Prediction, Prediction3D, Unicorn, world_verts
from unicorn.model.compile import CompileWarning, compile_networks
from unicorn.model.compositing import (
    DirectCompositing,
    ReferenceCompositing,
    build_compositing,
    list_compositings,
    register_compositing,
)
from unicorn.model.config import DEFAULT_CONFIG, UnicornConfig, check_model_config, merge_config
from unicorn.model.encoder import ResNet18
from unicorn.model.field import DeformationField, ShapeHead
from unicorn.model.generator import CodeGenerator, GiraffeGenerator
from unicorn.model.mlp import MLP
from unicorn.model.pose import PoseHead, PoseOutput, ScaleHead, mirrored_pose
from unicorn.model.progressive import ProgressiveMask, active_dims_at
from unicorn.model.size import MAX_MODEL_PARAMS, MAX_MODEL_PARAMS_ENV, check_model_size, count_parameters
from unicorn.model.template import TemplateMesh

__all__ = [
    "MAX_MODEL_PARAMS",
    "MAX_MODEL_PARAMS_ENV",
    "check_model_size",
    "DEFAULT_CONFIG",
    "MLP",
    "CodeGenerator",
    "CompileWarning",
    "DeformationField",
    "DirectCompositing",
    "GiraffeGenerator",
    "PoseHead",
    "PoseOutput",
    "Prediction",
    "Prediction3D",
    "ProgressiveMask",
    "ReferenceCompositing",
    "ResNet18",
    "ScaleHead",
    "ShapeHead",
    "TemplateMesh",
    "Unicorn",
    "UnicornConfig",
    "active_dims_at",
    "build_compositing",
    "check_model_config",
    "compile_networks",
    "count_parameters",
    "list_compositings",
    "merge_config",
    "mirrored_pose",
    "register_compositing",
    "world_verts",
]
