"""Code diagnostics: the numbers against a hand-run forward pass and the collapse warning."""

from __future__ import annotations

import csv
import math
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

from tests.support.model import randomize_heads, tiny_config
from tests.support.training import build_run
from unicorn.config.schema import DiagnosticsConfig
from unicorn.geometry.cameras import pixel_to_ndc
from unicorn.lit import CodeDiagnostics, CollapseWarning, ViewpointWarning, code_diagnostics, pose_diagnostics
from unicorn.lit.diagnostics import VIEWPOINT_SEED, collapse_reasons, viewpoint_reasons
from unicorn.lit.run import fit
from unicorn.metrics import mesh_spread
from unicorn.model import Unicorn
from unicorn.model.pose import PoseOutput
from unicorn.objectives.viewpoint import viewpoint_check
from unicorn.render import RenderOverflowWarning, overflow, rasterize_meshes


def _model() -> Unicorn:
    torch.manual_seed(0)
    model = Unicorn(tiny_config("real")).eval()
    randomize_heads(model)
    model.set_active_dims(shape=2, texture=3, background=0)
    return model


class _LitStandIn(nn.Module):
    """What the callback uses of a UnicornLitModule: ``model``, ``stage``, ``device``, train / eval."""

    def __init__(self, model: Unicorn, stage: int = 1) -> None:
        super().__init__()
        self.model = model
        self.stage = torch.tensor(stage)

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")


def test_numbers_match_a_hand_run_forward_pass() -> None:
    model = _model()
    images = torch.rand(6, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    stats = code_diagnostics(model, images)
    assert set(stats) == {"shape", "texture", "background", "pose"}
    with torch.no_grad():
        feats = model.encoders[0](images)  # the small model's shared encoder
    for branch in ("shape", "texture", "background"):
        x, hidden = feats, []
        for layer in getattr(model, branch).regressor:
            with torch.no_grad():
                x = layer(x.clone())
            if isinstance(layer, nn.ReLU):
                hidden.append(x.numpy().copy())
        code = x.numpy()
        active = getattr(model, branch).mask.active_dims
        s = stats[branch]
        assert s["active-dims"] == active
        assert s["raw-std"] == pytest.approx(np.std(code, axis=0).mean(), rel=1e-4)
        if active:
            assert s["code-std"] == pytest.approx(np.std(code[:, :active], axis=0).mean(), rel=1e-4)
            assert s["code-std-min"] == pytest.approx(np.std(code[:, :active], axis=0).min(), rel=1e-4)
        else:
            assert math.isnan(s["code-std"])
        last = hidden[-1]
        assert s["alive-last"] == sum(any(last[b, u] > 0 for b in range(6)) for u in range(last.shape[1]))
        assert s["units-last"] == last.shape[1]
        alive = sum(int((h > 0).any(axis=0).sum()) for h in hidden)
        assert s["alive-frac"] == pytest.approx(alive / sum(h.shape[1] for h in hidden))
    with torch.no_grad():
        canonical = model.predict(images).canonical_verts
    assert stats["shape"]["mesh-spread"] == pytest.approx(mesh_spread(canonical))
    assert stats["shape"]["mesh-spread"] > 0  # randomised heads: the shapes follow the images
    # hooks are removed and nothing in the model changed
    assert all(not layer._forward_hooks for layer in model.modules())


def test_a_collapsed_branch_warns_loudly(tmp_path) -> None:
    model = _model()
    callback = CodeDiagnostics(every_n_steps=1, max_images=8)
    trainer = SimpleNamespace(global_step=5, loggers=[], default_root_dir=str(tmp_path))
    module = _LitStandIn(model)
    callback._images.extend(torch.rand(8, 3, 32, 32, generator=torch.Generator().manual_seed(2)).unbind(0))
    row = callback.check(trainer, module)
    assert row is not None and callback.collapsed == {}
    assert row["shape/alive-last"] > 0 and row["texture/code-std"] > 1e-4

    # every unit of the shape regressor's last hidden layer dead: a constant code
    last_hidden = [m for m in model.shape.regressor if isinstance(m, nn.Linear)][-2]
    with torch.no_grad():
        last_hidden.bias.fill_(-1e4)
    # and a texture regressor whose output ignores the image
    with torch.no_grad():
        model.texture.regressor[-1].weight.zero_()
    trainer.global_step = 6
    with pytest.warns(CollapseWarning) as caught:
        row = callback.check(trainer, module)
    text = " ".join(str(w.message) for w in caught)
    assert "shape branch collapsed at iteration 6" in text and "dead ReLUs" in text
    assert "texture branch collapsed" in text and "ignores the image" in text
    assert row["shape/alive-last"] == 0 and row["texture/code-std"] == 0
    assert set(callback.collapsed) == {"shape", "texture"} and module.training  # mode restored
    # a collapse is reported once, not at every check
    trainer.global_step = 7
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", CollapseWarning)
        callback.check(trainer, module)
    rows = list(csv.DictReader(open(tmp_path / "diagnostics.csv", encoding="utf-8")))
    assert [r["step"] for r in rows] == ["5", "6", "7"] and rows[1]["shape/alive-last"] == "0.0"
    # a code size that just changed is not judged on its spread (new dimensions start at 0), dead units are
    fresh = CodeDiagnostics(every_n_steps=1, max_images=8)
    fresh._images.extend(callback._images)
    with pytest.warns(CollapseWarning) as caught:
        fresh.check(trainer, module)
    assert set(fresh.collapsed) == {"shape"} and "dead ReLUs" in str(caught[0].message)
    with pytest.raises(ValueError, match="max_images"):
        CodeDiagnostics(max_images=1)


def test_a_shape_code_far_less_spread_than_the_texture_code_warns(tmp_path) -> None:
    stats = {"active-dims": 4.0, "code-std": 0.005, "alive-last": 27.0, "units-last": 64.0}
    # the main job's numbers: shape 0.005 against texture 0.50, far above the absolute tolerance
    assert collapse_reasons(stats, 1e-6) == []
    reasons = collapse_reasons(stats, 1e-6, reference=("texture", 0.5), min_ratio=0.05)
    assert len(reasons) == 1 and "0.01 of the texture code's 0.5 (below 0.05)" in reasons[0]
    assert collapse_reasons(stats, 1e-6, reference=("texture", 0.09), min_ratio=0.05) == []  # 0.056 of it: fine
    assert collapse_reasons(stats, 1e-6, judge_spread=False, reference=("texture", 0.5), min_ratio=0.05) == []

    # in the callback: a shape code scaled down to 1 % of its spread (the texture code's is untouched)
    model = _model()
    images = torch.rand(8, 3, 32, 32, generator=torch.Generator().manual_seed(3))
    base = code_diagnostics(model, images)
    ratio = base["shape"]["code-std"] / base["texture"]["code-std"]
    assert ratio > 0.05  # the untrained model's codes vary alike
    with torch.no_grad():  # the code's variation is its last layer's weight times the hidden units'
        model.shape.regressor[-1].weight.mul_(0.01 * 0.05 / ratio)
    trainer = SimpleNamespace(global_step=5, loggers=[], default_root_dir=str(tmp_path))
    module = _LitStandIn(model)
    for threshold, warns in ((DiagnosticsConfig.shape_spread_ratio, True), (0.0, False)):
        callback = CodeDiagnostics(every_n_steps=1, max_images=8, shape_spread_ratio=threshold)
        callback._images.extend(images.unbind(0))
        callback._dims = {b: base[b]["active-dims"] for b in ("shape", "texture", "background")}  # sizes settled
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            row = callback.check(trainer, module)
        assert row["shape/code-std"] < 0.05 * row["texture/code-std"] and row["shape/code-std"] > 1e-6
        assert ("shape" in callback.collapsed) is warns
        assert any(issubclass(w.category, CollapseWarning) for w in caught) is warns
    with pytest.raises(ValueError, match="shape_spread_ratio"):
        CodeDiagnostics(shape_spread_ratio=-1.0)


def _poses(azim: list[list[float]], probs: list[list[float]]) -> PoseOutput:
    angles = torch.zeros(len(azim), len(azim[0]), 3)
    angles[..., 0] = torch.tensor(azim)
    p = torch.tensor(probs)
    return PoseOutput(
        angles=angles, R=torch.eye(3).expand(*p.shape, 3, 3), T=torch.zeros(*p.shape, 3), probs=p, log_probs=p.log()
    )


def test_pose_diagnostics_against_a_loop() -> None:
    # 3 candidates, 5 images: images 0, 1, 3 choose candidate 0, image 2 candidate 2, image 4 candidate 1
    azim = [[10.0, 20.0, 0.0, 40.0, 0.0], [60.0, 60.0, 60.0, 60.0, 75.0], [120.0, 120.0, 130.0, 120.0, 120.0]]
    probs = [[0.6, 0.5, 0.1, 0.7, 0.2], [0.2, 0.3, 0.2, 0.1, 0.5], [0.2, 0.2, 0.7, 0.2, 0.3]]
    out = pose_diagnostics(_poses(azim, probs), azim_half_range=30.0)
    assert out["share-min"] == pytest.approx(0.2) and out["share-max"] == pytest.approx(0.6)
    # only candidate 0 is chosen twice or more: azimuths 10, 20, 40
    assert out["azim-spread"] == pytest.approx(float(np.std([10.0, 20.0, 40.0])) / 30.0)
    # every image on its own candidate: no spread to measure; a fixed azimuth: no spread at all
    assert math.isnan(pose_diagnostics(_poses([[0.0, 5.0], [0.0, 9.0]], [[0.9, 0.1], [0.1, 0.9]]), 30.0)["azim-spread"])
    assert pose_diagnostics(_poses([[0.0, 5.0]], [[1.0, 1.0]]), 0.0)["azim-spread"] == 0.0


def test_pose_numbers_in_the_model_diagnostics(tmp_path) -> None:
    model = _model()
    images = torch.rand(8, 3, 32, 32, generator=torch.Generator().manual_seed(4))
    stats = code_diagnostics(model, images)
    with torch.no_grad():
        poses = model.predict(images).poses
    want = pose_diagnostics(poses, float(model.pose.R_range[0]))
    want.update(viewpoint_check(model, images, torch.Generator().manual_seed(VIEWPOINT_SEED)))
    assert stats["pose"] == want
    assert stats["pose"]["azim-spread"] > 0 or math.isnan(stats["pose"]["azim-spread"])  # randomised heads vary
    callback = CodeDiagnostics(every_n_steps=1, max_images=8)
    callback._images.extend(images.unbind(0))
    row = callback.check(SimpleNamespace(global_step=1, loggers=[], default_root_dir=str(tmp_path)), _LitStandIn(model))
    assert row["pose/share-max"] == stats["pose"]["share-max"] and "pose" not in callback.collapsed


# in a training run (rows in diagnostics.csv, training unchanged): tests/lit/test_heldout.py


def test_pose_shares_and_azimuth_bins_against_a_loop() -> None:
    azim = [[10.0, 40.0, 200.0, 350.0], [95.0, 100.0, 110.0, 300.0]]  # K = 2 candidates, B = 4 images
    probs = [[0.9, 0.2, 0.8, 0.7], [0.1, 0.8, 0.2, 0.3]]
    out = pose_diagnostics(_poses(azim, probs), 30.0)
    assert (out["share-0"], out["share-1"]) == (0.75, 0.25)
    # selected azimuths 10, 100, 200, 350: bins 0, 3, 6, 11 of twelve
    assert out["azim-bins"] == 4 / 12


def test_viewpoint_reasons() -> None:
    healthy = {"render-acc": 0.8, "render-azim-error": 12.0, "render-chance": 1 / 6, "share-max": 0.3}
    assert viewpoint_reasons(healthy, 0.5, 0.9) == []
    misread = viewpoint_reasons({**healthy, "render-acc": 0.2}, 0.5, 0.9)
    assert len(misread) == 1 and "20%" in misread[0] and "a guess 17%" in misread[0]
    one = viewpoint_reasons({**healthy, "share-max": 0.95}, 0.5, 0.9)
    assert one == ["one candidate is the most likely for 95% of the images"]
    assert viewpoint_reasons({**healthy, "render-acc": 0.0, "share-max": 1.0}, 0.0, 1.0) == []  # not judged


@pytest.mark.parametrize("stage", [1, 2])
def test_a_viewpoint_collapse_warns_from_stage_2(tmp_path, stage: int) -> None:
    """An untrained pose branch misreads renders at known views: judged (and warned about once) from stage 2 on."""
    model = _model()
    callback = CodeDiagnostics(every_n_steps=1, max_images=8, viewpoint_acc_tol=0.9)
    callback._images.extend(torch.rand(8, 3, 32, 32, generator=torch.Generator().manual_seed(2)).unbind(0))
    trainer = SimpleNamespace(global_step=5, loggers=[], default_root_dir=str(tmp_path))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        row = callback.check(trainer, _LitStandIn(model, stage=stage))
        trainer.global_step = 6
        callback.check(trainer, _LitStandIn(model, stage=stage))
    assert row is not None and row["pose/render-acc"] < 0.9
    viewpoint = [w for w in caught if issubclass(w.category, ViewpointWarning)]
    assert len(viewpoint) == (1 if stage == 2 else 0)
    assert bool(callback.viewpoint_collapsed) is (stage == 2)
    if stage == 2:
        assert "VIEWPOINT COLLAPSE: viewpoint learning collapsed at iteration 5" in str(viewpoint[0].message)
        assert callback.state_dict()["viewpoint_collapsed"] == callback.viewpoint_collapsed
        header = (tmp_path / "diagnostics.csv").read_text().splitlines()[0].split(",")
        assert {"pose/render-acc", "pose/render-azim-error", "pose/share-0", "pose/azim-bins"} <= set(header)


def _overlapping_triangles(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` random triangles given in NDC at depths 1..n: verts (1, 3n, 3) float64 and faces (n, 3)."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 3, 2, generator=g, dtype=torch.float64) * 2.4 - 1.2
    z = torch.arange(1, n + 1, dtype=torch.float64)[:, None, None].expand(n, 3, 1)
    return torch.cat([xy, z], -1).reshape(1, 3 * n, 3), torch.arange(3 * n).reshape(n, 3)


def _naive_overflow(verts: torch.Tensor, faces: torch.Tensor, size: int, K: int) -> int:
    """Pixels whose centre lies in more than K of the triangles (a loop over pixels and triangles)."""
    tris = verts[0, :, :2][faces].tolist()
    count = 0
    for row in range(size):
        for col in range(size):
            px, py = pixel_to_ndc(torch.tensor([float(col), float(row)], dtype=torch.float64), size).tolist()
            inside = 0
            for a, b, c in tris:
                d = [(v[0] - u[0]) * (py - u[1]) - (v[1] - u[1]) * (px - u[0]) for u, v in ((a, b), (b, c), (c, a))]
                inside += all(x > 0 for x in d) or all(x < 0 for x in d)
            count += inside > K
    return count


def test_the_overflow_share_is_logged_and_said_once_per_run(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(overflow, "_WARNED", set())  # a render outside a counter would warn, whatever ran before
    model = _model()
    callback = CodeDiagnostics(every_n_steps=1, max_images=8)
    callback._images.extend(torch.rand(8, 3, 32, 32, generator=torch.Generator().manual_seed(5)).unbind(0))
    logged: list[dict[str, float]] = []
    logger = SimpleNamespace(log_metrics=lambda metrics, step: logged.append(metrics))
    trainer = SimpleNamespace(global_step=0, loggers=[logger], default_root_dir=str(tmp_path))
    module = _LitStandIn(model)
    size, K = 16, 2
    callback.on_fit_start(trainer, module)
    try:
        shares, caught_all = [], []
        for seed, step in ((0, 3), (1, 6)):
            verts, faces = _overlapping_triangles(8, seed)
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # a render during fit does not warn by itself
                for _ in range(2):  # two renders of the same meshes between the checks
                    rasterize_meshes(verts, faces, size, 0.0, K)
            shares.append(_naive_overflow(verts, faces, size, K) / (size * size))
            trainer.global_step = step
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                callback.check(trainer, module)
            caught_all += [w for w in caught if issubclass(w.category, RenderOverflowWarning)]
        trainer.global_step = 7
        callback.check(trainer, module)  # nothing rendered since the previous check
    finally:
        callback.on_fit_end(trainer, module)
    assert min(shares) > 0
    rows = list(csv.DictReader(open(tmp_path / "diagnostics.csv", encoding="utf-8")))
    assert [float(r["render/overflow-share"]) for r in rows[:2]] == pytest.approx(shares, abs=1e-12)
    assert rows[2]["render/overflow-share"] == "nan"
    assert [m["diagnostics/render/overflow-share"] for m in logged[:2]] == pytest.approx(shares, abs=1e-12)
    # once per run, with the share and the setting to change; not again at the second check
    assert len(caught_all) == 1
    text = str(caught_all[0].message)
    assert f"iterations 0-3, {100 * shares[0]:.2g}% of the 512 pixels rendered with faces_per_pixel=2" in text
    assert "renderer.faces_per_pixel=N above 2" in text
    # after fit the renderer warns by itself again
    with pytest.warns(RenderOverflowWarning):
        rasterize_meshes(*_overlapping_triangles(8, 0), size, 0.0, K)


def test_a_training_run_says_the_overflow_once(synthetic_cache, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(overflow, "_WARNED", set())  # a render outside a counter would warn, whatever ran before
    run = build_run(
        tmp_path,
        "renderer.faces_per_pixel=1",
        "callbacks.diagnostics.every_n_steps=2",
        "callbacks.diagnostics.max_images=8",
        "trainer.max_steps=4",
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit(run)
    # none from the training steps' renders: one, from the first check, naming the share it logged
    said = [w for w in caught if issubclass(w.category, RenderOverflowWarning)]
    assert len(said) == 1 and said[0].filename.endswith("diagnostics.py"), [str(w.message) for w in said]
    rows = list(csv.DictReader(open(run.output_dir / "diagnostics.csv", encoding="utf-8")))
    share = float(rows[0]["render/overflow-share"])
    assert [r["step"] for r in rows] == ["2", "4"] and 0 < share < 1
    assert f"iterations 0-2, {100 * share:.2g}% of the" in str(said[0].message)
    assert "renderer.faces_per_pixel=N above 1 (e.g. 2" in str(said[0].message)
