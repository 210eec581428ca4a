"""UNICORN's training floor: the loss functions, the training objectives and test-time refinement.

The model (:class:`unicorn.model.Unicorn`) predicts and renders; the objectives take it and a batch and return
weighted loss terms with the batch's pose probabilities (:class:`StepLosses`). Each step detaches what the paper
says, so only its own branches receive gradients.

- :class:`Objectives`: the two steps built from a model configuration's ``loss`` group, by step kind
  (``"pose"``, ``"3d"``), and the training state they hold (the neighbour memory).
- ``loss_factory``: :func:`build_losses`, the reconstruction and mesh-regulariser modules of a ``loss`` group,
  built in one place for the training steps and for refinement.
- ``losses``: the loss functions (MSE, reconstruction terms, normal consistency, Laplacian, pose prior, candidate
  spacing and assignment).
- ``perceptual``: the perceptual losses chosen by name (``loss.perceptual``: VGG16, structural;
  :func:`build_perceptual`, :func:`register_perceptual`).
- ``pose_objectives``: the pose objectives chosen by name (``loss.pose_objective``: :class:`ExpectedLoss`,
  :class:`AssignedLoss`, :class:`AssignedBestLoss`, sampled; :func:`register_pose_objective`).
- ``viewpoint``: supervision of the pose branch by rendered viewpoints (``loss.viewpoint``).
- ``pose_step``: :class:`PoseStep`; ``shape_step``: :class:`ShapeStep` (the 3D step).
- ``neighbors``: :class:`NeighborLoss` and its memory bank (:class:`NeighborMemory`).
- ``refine``: test-time refinement of a prediction against its image
  (:func:`unicorn.objectives.refine.refine`, :class:`RefineOptions`).
"""

from unicorn.objectives.loss_factory import ImageLosses, build_losses
from unicorn.objectives.losses import (
    MeshRegularizer,
    NormalConsistencyLoss,
    ReconstructionLoss,
    UniformLaplacianLoss,
    candidate_assignment_loss,
    candidate_spacing_loss,
    flip_consistency_loss,
    mse_per_sample,
    uniform_pose_prior,
    view_equivariance_loss,
)
from unicorn.objectives.neighbors import NeighborLoss, NeighborMatch, NeighborMemory
from unicorn.objectives.objectives import Objectives, training_networks
from unicorn.objectives.perceptual import (
    StructuralLoss,
    VGGPerceptualLoss,
    build_perceptual,
    list_perceptual_losses,
    load_vgg16_weights,
    register_perceptual,
)
from unicorn.objectives.pose_objectives import (
    AllCandidates,
    AssignedBestLoss,
    AssignedLoss,
    ExpectedLoss,
    PoseObjective,
    SampledCandidates,
    build_pose_objective,
    list_pose_objectives,
    register_pose_objective,
)
from unicorn.objectives.pose_step import PoseStep
from unicorn.objectives.refine import Refinement, RefineOptions
from unicorn.objectives.shape_step import ShapeStep
from unicorn.objectives.step_losses import StepLosses

__all__ = [
    "AllCandidates",
    "AssignedBestLoss",
    "AssignedLoss",
    "ExpectedLoss",
    "ImageLosses",
    "MeshRegularizer",
    "NeighborLoss",
    "NeighborMatch",
    "NeighborMemory",
    "NormalConsistencyLoss",
    "Objectives",
    "PoseObjective",
    "PoseStep",
    "ReconstructionLoss",
    "RefineOptions",
    "Refinement",
    "SampledCandidates",
    "ShapeStep",
    "StepLosses",
    "StructuralLoss",
    "UniformLaplacianLoss",
    "VGGPerceptualLoss",
    "build_losses",
    "build_perceptual",
    "build_pose_objective",
    "candidate_assignment_loss",
    "candidate_spacing_loss",
    "flip_consistency_loss",
    "list_perceptual_losses",
    "list_pose_objectives",
    "load_vgg16_weights",
    "mse_per_sample",
    "register_perceptual",
    "register_pose_objective",
    "training_networks",
    "uniform_pose_prior",
    "view_equivariance_loss",
]
