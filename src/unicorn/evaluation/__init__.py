"""Evaluation of trained models and reconstruction of user images (the library behind ``unicorn-eval`` and
``unicorn-reconstruct``).

- :mod:`~unicorn.evaluation.interface`: what a model must offer to be evaluated (:class:`EvaluableModel`);
- :mod:`~unicorn.evaluation.protocols`: what each protocol scores (:data:`PROTOCOL_REGISTRY`), the options and
  the result records;
- :mod:`~unicorn.evaluation.evaluator`: the evaluation loop (:func:`evaluate`), with the measurements of each
  family of metrics in :mod:`~unicorn.evaluation.measurements`;
- :mod:`~unicorn.evaluation.session`: one evaluation into a folder, metrics and report (what ``unicorn-eval``
  and ``unicorn-train`` run);
- :mod:`~unicorn.evaluation.rendering`: hard renders for masks, visibility, mesh views and turntables;
- :mod:`~unicorn.evaluation.metric_files`: metric tables (text, CSV, JSON); :mod:`~unicorn.evaluation.report`:
  the visual report (PNG grid, HTML), with :mod:`~unicorn.evaluation.pictures`;
- :mod:`~unicorn.evaluation.reconstruct`: per-image meshes, pictures, masks, poses and turntables;
- :mod:`~unicorn.evaluation.baselines`: the reference baselines (template at the anchor pose, mean training
  shape) as :class:`FixedShapeModel` instances that :func:`evaluate` scores like any model; the mean shape's fit in
  :mod:`~unicorn.evaluation.mean_shape`.

Every function takes an :class:`EvaluableModel` (a :class:`~unicorn.model.Unicorn` or a baseline);
:func:`unicorn.io.load_model` reads any checkpoint.
"""

from unicorn.evaluation.baselines import (
    FixedShapeModel,
    fit_silhouettes,
    mean_shape_baseline,
    template_baseline,
    training_point_clouds,
)
from unicorn.evaluation.evaluator import build_eval_dataset, candidate_shares, evaluate
from unicorn.evaluation.interface import EvaluableModel
from unicorn.evaluation.mean_shape import fit_mean_shape
from unicorn.evaluation.metric_files import format_table, write_metrics
from unicorn.evaluation.protocols import (
    PROTOCOL_REGISTRY,
    EvalOptions,
    EvaluationResult,
    Protocol,
    Sample,
    get_protocol,
    protocol_for,
)
from unicorn.evaluation.reconstruct import reconstruct
from unicorn.evaluation.rendering import hard_render, shaded_render, turntable, vertex_visibility
from unicorn.evaluation.report import write_report

__all__ = [
    "PROTOCOL_REGISTRY",
    "EvalOptions",
    "EvaluableModel",
    "EvaluationResult",
    "FixedShapeModel",
    "Protocol",
    "Sample",
    "build_eval_dataset",
    "candidate_shares",
    "evaluate",
    "fit_mean_shape",
    "get_protocol",
    "fit_silhouettes",
    "format_table",
    "hard_render",
    "mean_shape_baseline",
    "protocol_for",
    "reconstruct",
    "shaded_render",
    "template_baseline",
    "training_point_clouds",
    "turntable",
    "vertex_visibility",
    "write_metrics",
    "write_report",
]
