"""The pose objectives (unicorn.model.pose_objectives): how each weights the candidates' terms."""

from __future__ import annotations

import pytest
import torch

from unicorn.model.pose_objectives import build_pose_objective, list_pose_objectives


def test_pose_objectives_weight_the_candidates_terms():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(3, 4, generator=g, requires_grad=True)  # K = 3 candidates, B = 4 images
    log_probs = torch.log_softmax(logits, 0)
    probs = log_probs.exp()
    terms = {"rgb": torch.rand(12, generator=g), "perceptual": torch.rand(12, generator=g)}
    expected = build_pose_objective("expected")(probs, log_probs, terms)
    assigned = build_pose_objective("assigned", assignment_weight=0.5, uniform_weight=9.0)(probs, log_probs, terms)
    for name, value in terms.items():
        want = (probs * value.view(3, 4)).sum(0).mean()
        torch.testing.assert_close(expected[name], want)
        torch.testing.assert_close(assigned[name], want)
    best = (terms["rgb"] + terms["perceptual"]).view(3, 4).argmin(0)
    torch.testing.assert_close(assigned["assignment"], 0.5 * -log_probs[best, torch.arange(4)].mean())
    assert set(expected) == {"rgb", "perceptual"}
    # the assigned objective's reconstruction terms do not reach the probabilities
    assert not assigned["rgb"].requires_grad and expected["rgb"].requires_grad
    assert list_pose_objectives() == ["assigned", "assigned_best", "expected"]
    with pytest.raises(ValueError, match=r"unknown pose_objective 'best'; known: \['assigned', 'assigned_best', 'exp"):
        build_pose_objective("best")


def test_assigned_best_refines_only_the_best_candidates_pose():
    g = torch.Generator().manual_seed(1)
    K, B = 3, 5
    logits = torch.randn(K, B, generator=g, requires_grad=True)
    log_probs = torch.log_softmax(logits, 0)
    pose = torch.rand(K * B, generator=g, requires_grad=True)  # stands for each candidate's pose, candidate-major
    terms = {"rgb": (pose - 0.3) ** 2, "perceptual": 0.5 * torch.rand(K * B, generator=g)}
    out = build_pose_objective("assigned_best", assignment_weight=0.5)(log_probs.exp(), log_probs, terms)
    assert set(out) == {"rgb", "perceptual", "assignment"}
    # a naive loop: each image's terms at the candidate whose summed terms are lowest
    total = [[float(terms["rgb"][k * B + b] + terms["perceptual"][k * B + b]) for k in range(K)] for b in range(B)]
    best = [min(range(K), key=lambda k: row[k]) for row in total]
    for name, value in terms.items():
        want = sum(float(value[best[b] * B + b]) for b in range(B)) / B
        assert out[name].item() == pytest.approx(want, rel=1e-6)
    want = -sum(float(log_probs[best[b], b]) for b in range(B)) / B
    assert out["assignment"].item() == pytest.approx(0.5 * want, rel=1e-6)
    assert len(set(best)) > 1  # the case where weighting matters: different candidates win
    # the reconstruction terms reach the winners' poses only, and never the probabilities
    (out["rgb"] + out["perceptual"]).backward()
    winners = {best[b] * B + b for b in range(B)}
    assert [i for i in range(K * B) if pose.grad[i] != 0] == sorted(winners)
    assert logits.grad is None
