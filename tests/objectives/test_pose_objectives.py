"""The pose objectives (unicorn.objectives.pose_objectives): how each weights the candidates' terms."""

from __future__ import annotations

import pytest
import torch

from unicorn.objectives.pose_objectives import build_pose_objective, list_pose_objectives


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
    assert list_pose_objectives() == ["assigned", "assigned_best", "expected", "sampled"]
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


def test_sampled_schedule_picks_random_then_mostly_the_most_likely():
    objective = build_pose_objective(
        "sampled",
        sample_random_until=100,
        sample_ramp=100,
        sample_random_share=0.2,
        sample_uniform_until=50,
        sample_tau_period=10,
    )
    # the random share: 1 until 100, linear to 0.2 at 200, then 0.2
    assert [objective.random_share(i) for i in (0, 99, 100, 150, 200, 10_000)] == pytest.approx(
        [1.0, 1.0, 1.0, 0.6, 0.2, 0.2]
    )
    # the temperature: 1 / clip(iteration / 10, 1, 100)
    assert [objective.temperature(i) for i in (0, 10, 20, 500, 5000)] == pytest.approx([1, 1, 0.5, 0.02, 0.01])
    K, B = 4, 4000
    logits = torch.zeros(K, B)
    logits[2] = 1.0  # candidate 2 most likely for every image
    torch.manual_seed(0)
    for iteration, share in ((0, 1.0), (150, 0.6), (300, 0.2)):
        picked = objective.pick(logits, iteration)
        # random picks land on candidate 2 a quarter of the time: P(2) = 1 - share + share / K
        assert (picked == 2).float().mean().item() == pytest.approx(1 - share + share / K, abs=0.03)
    # uniform probabilities until sample_uniform_until, softmax(logits / tau) after
    torch.testing.assert_close(objective.probabilities(logits[:, :3], 10), torch.full((K, 3), 0.25))
    torch.testing.assert_close(objective.probabilities(logits[:, :3], 60), torch.softmax(logits[:, :3] / (1 / 6), 0))


def test_sampled_terms_weight_the_picked_candidates_and_regress_their_scores():
    objective = build_pose_objective("sampled", score_weight=0.5, sample_uniform_until=0, sample_tau_period=1000)
    g = torch.Generator().manual_seed(2)
    K, B = 3, 5
    logits = torch.randn(K, B, generator=g, requires_grad=True)
    picked = torch.tensor([0, 2, 1, 1, 0])
    pose = torch.rand(B, generator=g, requires_grad=True)
    terms = {"rgb": (pose - 0.3) ** 2, "perceptual": torch.rand(B, generator=g)}
    out = objective(logits, picked, terms, iteration=500)  # tau = 1
    p = torch.softmax(logits.detach(), 0)
    for name, value in terms.items():
        want = sum(min(1.0, K * float(p[picked[b], b])) * float(value[b]) for b in range(B)) / B
        assert out[name].item() == pytest.approx(want, rel=1e-6)
    loss = terms["rgb"].detach() + terms["perceptual"]
    want = sum((-float(logits[picked[b], b]) - float(loss[b])) ** 2 for b in range(B)) / B
    assert out["score"].item() == pytest.approx(0.5 * want, rel=1e-6)
    # the score term reaches the picked logits only; the reconstruction terms never reach the logits
    out["score"].backward()
    reached = [(k, b) for b in range(B) for k in range(K) if logits.grad[k, b] != 0]
    assert reached == [(int(picked[b]), b) for b in range(B)]
    out["rgb"].backward()
    assert pose.grad is not None and (logits.grad != 0).sum() == B  # unchanged: rgb's weights are detached


def test_sampled_options_are_checked():
    with pytest.raises(ValueError, match="sample_random_share"):
        build_pose_objective("sampled", sample_random_share=1.5)
    with pytest.raises(ValueError, match="sample_tau_period"):
        build_pose_objective("sampled", sample_tau_period=0)
