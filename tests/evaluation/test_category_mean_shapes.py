"""The mean-shape baseline of an evaluation (``unicorn-eval --mean-shape``): each category's own mean training shape."""

from __future__ import annotations

import logging

import pytest
import torch

from unicorn.checks import ShapeError
from unicorn.evaluation import EvalOptions, build_eval_dataset, evaluate, fit_mean_shape, training_point_clouds
from unicorn.evaluation import mean_shape as mean_shape_module
from unicorn.evaluation.session import EvalTarget, evaluate_to_folder

ITERATIONS = 20
OPTIONS = dict(num_points=300, icp_iterations=2, report_samples=0, progress=False, shape_points=0)
COLUMNS = ("chamfer-L1-ICP-mean-shape", "shape-win")


def _alone(model, root, category: str) -> torch.Tensor:
    """The category's mean shape fitted on its own training shapes, as ``unicorn-eval`` fits one (200 models of 5000
    points, the evaluation's seed)."""
    clouds = training_point_clouds(root, category, max_models=200, num_points=5000)
    return fit_mean_shape(model.template.verts, model.template.faces, clouds, iterations=ITERATIONS, seed=0)


def _scored(model, root, categories, tmp_path, **options):
    target = EvalTarget("synthetic", str(root), "train", categories)
    result, _ = evaluate_to_folder(
        model, target, EvalOptions("shapenet", **{**OPTIONS, **options}), tmp_path, {},
        mean_shape_iterations=ITERATIONS,
    )  # fmt: skip
    return result


def test_each_category_is_scored_against_its_own_mean_shape(shapenet_model, synth_root, tmp_path) -> None:
    result = _scored(shapenet_model, synth_root, None, tmp_path)
    assert {row["group"] for row in result.per_image} == {"chair", "mug"}
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    for category in ("chair", "mug"):
        # the oracle: the whole split scored against the mean shape of that category fitted alone
        alone = evaluate(
            shapenet_model, data, EvalOptions("shapenet", **OPTIONS), "synthetic",
            shape_baseline=_alone(shapenet_model, synth_root, category),
        )  # fmt: skip
        rows = [(got, want) for got, want in zip(result.per_image, alone.per_image) if got["group"] == category]
        assert rows and all(got["index"] == want["index"] for got, want in rows)
        for column in COLUMNS:
            assert [got[column] for got, _ in rows] == pytest.approx([want[column] for _, want in rows], rel=1e-6)


def test_one_category_is_scored_as_before(shapenet_model, synth_root, tmp_path) -> None:
    # one category: its mean shape is that of all the training shapes evaluated, bit for bit
    result = _scored(shapenet_model, synth_root, ["mug"], tmp_path)
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32, categories=["mug"])
    shape = _alone(shapenet_model, synth_root, "mug")
    alone = evaluate(shapenet_model, data, EvalOptions("shapenet", **OPTIONS), "synthetic", shape_baseline=shape)
    assert result.per_image == alone.per_image and result.table == alone.table


def test_a_mapping_of_group_meshes(shapenet_model, synth_root) -> None:
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    options = EvalOptions("shapenet", **OPTIONS)
    template = shapenet_model.template.verts.clone()
    one = evaluate(shapenet_model, data, options, "synthetic", shape_baseline=template * 0.9)
    per_group = {"chair": template * 0.9, "mug": template * 0.9}
    same = evaluate(shapenet_model, data, options, "synthetic", shape_baseline=per_group)
    for got, want in zip(same.per_image, one.per_image):
        assert [got[c] for c in COLUMNS] == pytest.approx([want[c] for c in COLUMNS], rel=1e-6)
    with pytest.raises(ValueError, match=r"^shape_baseline has no mesh for the evaluated group\(s\) \['mug'\]"):
        evaluate(shapenet_model, data, options, "synthetic", shape_baseline={"chair": template})
    with pytest.raises(ShapeError, match=r"shape_baseline\['mug'\]"):
        evaluate(shapenet_model, data, options, "synthetic", shape_baseline={"chair": template, "mug": template[:5]})


def test_no_mean_shape_is_fitted_without_icp(shapenet_model, synth_root, tmp_path, monkeypatch, caplog) -> None:
    def no_fit(*args, **kwargs):
        raise AssertionError("the mean shape is fitted, but it cannot be scored without ICP")

    monkeypatch.setattr(mean_shape_module, "_fit_offsets", no_fit)
    with caplog.at_level(logging.INFO, logger="unicorn.evaluation"):
        result = _scored(shapenet_model, synth_root, None, tmp_path, icp_iterations=0, own_mean_shape=True)
    assert not {*COLUMNS, "chamfer-L1-ICP-own-mean"} & set(result.columns)
    assert "no mean shape is fitted (mean_shape_iterations 20): it is scored after ICP" in caplog.text
    assert "the model's own average shape is not scored (own_mean_shape): it is scored after ICP" in caplog.text
