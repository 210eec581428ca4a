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
    gpu = evaluate(copy.deepcopy(shapenet_model).cuda(), data, options, "synthetic")
    for key in ("mask-iou", "chamfer-L1", "chamfer-L1-ICP", "rot-err-median"):
        assert gpu.mean[key] == pytest.approx(cpu.mean[key], rel=0.05, abs=0.01), key
