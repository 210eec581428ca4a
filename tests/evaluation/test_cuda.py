"""Evaluation on CUDA gives the CPU's numbers (run where CUDA is)."""

from __future__ import annotations

import copy

import pytest

from unicorn.evaluation import EvalOptions, build_eval_dataset, evaluate

pytestmark = pytest.mark.gpu


def test_shapenet_protocol_on_cuda_matches_cpu(shapenet_model, synth_root):
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    options = EvalOptions("shapenet", batch_size=3, num_points=400, icp_iterations=2, progress=False)
    cpu = evaluate(shapenet_model, data, options, "synthetic")
    gpu = evaluate(copy.deepcopy(shapenet_model).cuda(), data, options, "synthetic", device="cuda")
    for key in ("mask-iou", "chamfer-L1", "chamfer-L1-ICP", "rot-err-median"):
        assert gpu.mean[key] == pytest.approx(cpu.mean[key], rel=0.05, abs=0.01), key


def test_baselines_share_the_ground_truth_index_on_cuda(shapenet_model, synth_root):
    data = build_eval_dataset("synthetic", str(synth_root), "train", img_size=32)
    options = EvalOptions(
        "shapenet", batch_size=3, num_points=400, icp_iterations=5, progress=False, own_mean_shape=True
    )
    base = shapenet_model.template.verts * 0.9
    cpu = evaluate(shapenet_model, data, options, "synthetic", shape_baseline=base)
    gpu = evaluate(copy.deepcopy(shapenet_model).cuda(), data, options, "synthetic", device="cuda", shape_baseline=base)
    for key in ("chamfer-L1-ICP", "chamfer-L1-ICP-mean-shape", "chamfer-L1-ICP-own-mean", "normal-cos-ICP"):
        assert gpu.mean[key] == pytest.approx(cpu.mean[key], rel=0.05, abs=0.01), key
