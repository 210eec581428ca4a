"""Viewpoint self-supervision (unicorn.objectives.viewpoint): draws, renders, terms against direct computations, and
a pose branch trained on renders at known views learning their candidates."""

from __future__ import annotations

import math

import pytest
import torch

from tests.support.model import randomize_heads, tiny_config
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.model import Unicorn
from unicorn.model.pose import PoseHead, PoseOutput
from unicorn.objectives import Objectives
from unicorn.objectives.viewpoint import (
    DrawnViews,
    RenderedViewpoints,
    build_viewpoint_supervision,
    candidate_of,
    draw_views,
    list_viewpoint_supervisions,
    render_views,
    viewpoint_terms,
    wrap_degrees,
)


def _model(**loss) -> Unicorn:
    torch.manual_seed(0)
    model = Unicorn(tiny_config("real", loss=loss))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=3, background=2)
    return model


def test_candidate_of_matches_a_loop_over_anchors() -> None:
    head = PoseHead(16, n_elev=2, n_azim=6, elev_range=(-10, 30), roll_range=(-30, 30))
    g = torch.Generator().manual_seed(0)
    angles = torch.rand(200, 3, generator=g) * torch.tensor([720.0, 40.0, 60.0]) - torch.tensor([180.0, 10.0, 30.0])
    got = candidate_of(head, angles)
    for b in range(angles.shape[0]):
        costs = []
        for k in range(head.n_candidates):
            da = (float(angles[b, 0]) - float(head.R_init[k, 0]) + 180.0) % 360.0 - 180.0
            de = float(angles[b, 1]) - float(head.R_init[k, 1])
            costs.append((da / float(head.R_range[0])) ** 2 + (de / float(head.R_range[1])) ** 2)
        assert int(got[b]) == min(range(len(costs)), key=costs.__getitem__)
    # the sector's candidate can reach the view: within its offset range
    offset = wrap_degrees(angles[:, 0] - head.R_init[got, 0]).abs()
    assert bool((offset <= head.R_range[0]).all())


def test_wrap_degrees() -> None:
    got = wrap_degrees(torch.tensor([359.0, -181.0, 180.0, 10.0]))
    torch.testing.assert_close(got, torch.tensor([-1.0, 179.0, -180.0, 10.0]))


@pytest.mark.parametrize(("curriculum", "azimuth_only"), [(True, False), (False, False), (False, True)])
def test_draws_cover_the_ranges_and_follow_the_switches(curriculum: bool, azimuth_only: bool) -> None:
    head = PoseHead(16, n_azim=6, elev_range=(-10, 30), roll_range=(-30, 30), T_range=0.3)
    head.use_elevation_roll.fill_(not curriculum)
    head.use_translation.fill_(not curriculum)
    views = draw_views(head, 2000, torch.Generator().manual_seed(1), azimuth_only=azimuth_only)
    a = views.angles
    assert float(a[:, 0].min()) >= 0 and float(a[:, 0].max()) <= 360 and float(a[:, 0].max() - a[:, 0].min()) > 350
    torch.testing.assert_close(views.R, azim_elev_roll_to_rotation(a[:, 0], a[:, 1], a[:, 2]))
    torch.testing.assert_close(views.candidate, candidate_of(head, a))
    if curriculum or azimuth_only:  # held as the head holds them: every view is one the head can express
        torch.testing.assert_close(a[:, 1:], head.R_init[views.candidate, 1:])
        torch.testing.assert_close(views.T, head.T_init.expand(2000, 3))
    else:
        assert -10 <= float(a[:, 1].min()) < -9 and 29 < float(a[:, 1].max()) <= 30
        assert float((views.T - head.T_init).abs().max()) <= 0.3 + 1e-6
        assert float((views.T - head.T_init).abs().max()) > 0.29
    shares = torch.bincount(views.candidate, minlength=6).float() / 2000
    assert float(shares.min()) > 0.13  # uniform azimuths: each sector about a sixth


def test_renders_are_the_reconstructions_at_the_drawn_views() -> None:
    model = _model().eval()
    images = torch.rand(3, 3, 32, 32, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        pred = model.predict_3d(model.encode(images, model.branches()))
    views = draw_views(model.pose, 3, torch.Generator().manual_seed(3))
    own = render_views(model, pred, views, mix=0.0)
    with torch.no_grad():
        want, _ = model.render(pred.verts, pred.texture, views.R, views.T, pred.background[[2, 0, 1]])
    torch.testing.assert_close(own, want.clamp(0, 1))
    # mix = 1: every render blends two images, so the renders change (the blend weight is drawn in [0, 1])
    blended = render_views(model, pred, views, mix=1.0, generator=torch.Generator().manual_seed(4))
    assert not torch.allclose(blended, own)


def _poses(angles: torch.Tensor, T: torch.Tensor, logits: torch.Tensor) -> PoseOutput:
    log_probs = torch.log_softmax(logits, 0)
    R = azim_elev_roll_to_rotation(angles[..., 0], angles[..., 1], angles[..., 2])
    return PoseOutput(angles=angles, R=R, T=T, probs=log_probs.exp(), log_probs=log_probs)


def test_terms_against_a_direct_computation() -> None:
    head = PoseHead(16, n_azim=4, elev_range=(-10, 30), roll_range=(-30, 30), T_range=0.3)
    K, B = 4, 3
    g = torch.Generator().manual_seed(5)
    target = torch.tensor([[359.0, 5.0, 2.0], [91.0, -3.0, 0.0], [200.0, 10.0, -4.0]])
    R = azim_elev_roll_to_rotation(*target.T)
    views = DrawnViews(target, R, torch.rand(B, 3, generator=g), candidate_of(head, target))
    assert views.candidate.tolist() == [0, 1, 2]
    angles = target.expand(K, B, 3).clone()
    angles[0, 0, 0] = 1.0  # 2 degrees from 359, across the wrap
    angles[2, 2, 1] = 16.0  # 6 degrees of elevation
    T = views.T.expand(K, B, 3).clone()
    T[1, 1, 0] += 0.06
    logits = torch.randn(K, B, generator=g)
    logits[3, 2] = 10.0  # image 2's most likely candidate is not its view's
    poses = _poses(angles, T, logits)
    out = viewpoint_terms(poses, views, head)
    lp = torch.log_softmax(logits, 0)
    torch.testing.assert_close(out["ce"], -(lp[0, 0] + lp[1, 1] + lp[2, 2]) / 3)
    half = head.R_range
    want = ((2 / half[0]) ** 2 + (0.06 / 0.3) ** 2 + (6 / half[1]) ** 2) / 3
    torch.testing.assert_close(out["regression"], want)
    best = logits.argmax(0)
    torch.testing.assert_close(out["accuracy"], (best == views.candidate).float().mean())
    # while the head holds the elevation, roll and translation, their errors do not count
    head.use_elevation_roll.fill_(False)
    head.use_translation.fill_(False)
    torch.testing.assert_close(viewpoint_terms(poses, views, head)["regression"], (2 / half[0]) ** 2 / 3)


def test_azimuth_error_is_the_median_of_an_even_batch() -> None:
    head = PoseHead(16, n_azim=4, elev_range=(-10, 30), roll_range=(-30, 30), T_range=0.3)
    target = torch.tensor([[10.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
    views = DrawnViews(target, azim_elev_roll_to_rotation(*target.T), torch.zeros(2, 3), candidate_of(head, target))
    angles = target.expand(4, 2, 3).clone()
    angles[..., 0] += torch.tensor([10.0, 50.0])  # every candidate off by 10 and 50 degrees
    logits = torch.zeros(4, 2)
    out = viewpoint_terms(_poses(angles, views.T.expand(4, 2, 3), logits), views, head)
    torch.testing.assert_close(out["azim-error"], torch.tensor(30.0))  # not the lower middle value, 10


def test_registry_schedule_and_config() -> None:
    assert list_viewpoint_supervisions() == ["renders"]
    with pytest.raises(ValueError, match=r"unknown viewpoint 'views'; known: \['renders'\]"):
        build_viewpoint_supervision("views")
    sup = build_viewpoint_supervision("renders", viewpoint_start=10, viewpoint_every=3, rgb_weight=1.0)
    assert [i for i in range(10, 30, 2) if sup.active(i)] == [10, 16, 22, 28]
    assert not sup.active(8) and sup.active(None)
    with pytest.raises(ValueError, match="viewpoint_every"):
        RenderedViewpoints(viewpoint_every=0)
    model = Unicorn(tiny_config("real"))
    with pytest.raises(ValueError, match=r"loss.viewpoint must be one of \('renders', None\)"):
        Objectives.from_config({**model.config["loss"], "viewpoint": "render"}, model)


def test_the_pose_step_adds_the_terms_and_reaches_only_the_pose_branch() -> None:
    model = _model(viewpoint="renders", viewpoint_weight=0.3, viewpoint_pose_weight=0.2, viewpoint_start=4)
    objectives = Objectives.from_config(model.config["loss"], model)
    images = torch.rand(4, 3, 32, 32, generator=torch.Generator().manual_seed(6))
    before = objectives("pose", model, images, iteration=2)
    assert "viewpoint" not in before and not before.stats
    losses = objectives("pose", model, images, iteration=4)
    assert {"viewpoint", "viewpoint_pose"} <= set(losses)
    assert set(losses.stats) == {"viewpoint_accuracy", "viewpoint_azim_error"}
    torch.testing.assert_close(losses["total"], sum(v for k, v in losses.items() if k != "total"))
    model.zero_grad(set_to_none=True)
    losses["viewpoint"].backward(retain_graph=True)
    assert model.pose.proba_regressor[0].weight.grad is not None
    assert all(p.grad is None for p in model.texture.parameters())  # renders are detached from the 3D branches
    assert all(p.grad is None for p in model.shape.parameters())


def test_a_render_at_a_known_view_trains_the_scores_toward_its_candidate() -> None:
    """The oracle: the candidate whose sector holds the drawn azimuth. A pose branch trained on the renders alone
    learns to name it for new views of the same reconstructions, far above a guess (1 / 6)."""
    torch.manual_seed(0)
    model = Unicorn(tiny_config("real", size="tiny", encoder={"width": 16}))
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=3, background=2)
    model.set_stage_switches(elevation_roll=False, translation=False)
    images = torch.rand(8, 3, 32, 32, generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        pred = model.predict_3d(model.encode(images, model.branches()))
    # a texture whose colour turns with the azimuth (hue from the map's u coordinate): views can be told apart
    u = torch.linspace(0, 2 * math.pi, pred.texture.shape[-1])
    hue = torch.stack([u.cos(), (u + 2.1).cos(), (u + 4.2).cos()]) * 0.5 + 0.5  # (3, W)
    pred.texture = hue[None, :, None, :].expand_as(pred.texture).contiguous()
    supervision = RenderedViewpoints(viewpoint_weight=1.0, viewpoint_pose_weight=0.1, viewpoint_mix=0.0)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)

    def accuracy() -> float:  # 64 new views, the same at each call (batch statistics over the 64 renders)
        with torch.no_grad():
            views = draw_views(model.pose, 64, torch.Generator().manual_seed(99))
            many = {k: v.repeat(8, *[1] * (v.dim() - 1)) for k, v in vars(pred).items()}
            renders = render_views(model, type(pred)(**many), views)
            poses = model.pose(model.encode(renders, ("pose",))["pose"])
        return float(viewpoint_terms(poses, views, model.pose)["accuracy"])

    start = accuracy()
    for _ in range(150):
        terms, stats = supervision(model, pred)
        opt.zero_grad()
        (terms["viewpoint"] + terms["viewpoint_pose"]).backward()
        opt.step()
    end = accuracy()
    assert start < 0.35 and end > 0.6, (start, end)
