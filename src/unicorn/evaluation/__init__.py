"""Evaluation of trained models and reconstruction of user images (the library behind ``unicorn-eval`` and
``unicorn-reconstruct``).

- :mod:`~unicorn.evaluation.interface`: what a model must offer to be evaluated (:class:`EvaluableModel`);
- :mod:`~unicorn.evaluation.evaluator`: the evaluation protocols per dataset family (:func:`evaluate`);
- :mod:`~unicorn.evaluation.rendering`: hard renders for masks, visibility, mesh views and turntables;
- :mod:`~unicorn.evaluation.report`: metric tables (text, CSV, JSON) and the visual report (PNG grid, HTML);
- :mod:`~unicorn.evaluation.reconstruct`: per-image meshes, pictures, masks, poses and turntables;
- :mod:`~unicorn.evaluation.baselines`: the reference baselines (template at the anchor pose, mean training
  shape) as :class:`FixedShapeModel` instances that :func:`evaluate` scores like any model.

Every function takes an :class:`EvaluableModel` (a :class:`~unicorn.model.Unicorn` or a baseline);
:func:`unicorn.io.load_model` reads any checkpoint.
"""

from unicorn.evaluation.baselines import (
    FixedShapeModel,
    fit_mean_shape,
    fit_silhouettes,
    mean_shape_baseline,
    template_baseline,
    training_point_clouds,
)
from unicorn.evaluation.evaluator import (
    PROTOCOLS,
    EvalOptions,
    EvaluationResult,
    Sample,
    build_eval_dataset,
    candidate_shares,
    evaluate,
    protocol_for,
)
from unicorn.evaluation.interface import EvaluableModel
from unicorn.evaluation.reconstruct import reconstruct
from unicorn.evaluation.rendering import hard_render, shaded_render, turntable, vertex_visibility
from unicorn.evaluation.report import format_table, write_metrics, write_report

__all__ = [
    "PROTOCOLS",
    "EvalOptions",
    "EvaluableModel",
    "EvaluationResult",
    "FixedShapeModel",
    "Sample",
    "build_eval_dataset",
    "candidate_shares",
    "evaluate",
    "fit_mean_shape",
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
