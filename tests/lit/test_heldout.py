"""Held-out evaluation during training and the evaluation after it (``callbacks.heldout``, ``evaluate``)."""

from __future__ import annotations

import csv
import json
import re
import shlex
from types import SimpleNamespace

import pytest
import torch
from PIL import Image

from tests.support.evaluation import tiny_model
from tests.support.training import build_run, compose_config
from unicorn.cli.eval import build_parser as build_eval_parser
from unicorn.config import ConfigError, validate
from unicorn.config.schema import HeldOutConfig
from unicorn.evaluation import EvalOptions, build_eval_dataset, evaluate, fit_mean_shape, training_point_clouds
from unicorn.lit import CodeDiagnostics, HeldOutEvaluation
from unicorn.lit.run import fit

DIAGNOSTICS = ["callbacks.diagnostics.every_n_steps=4", "callbacks.diagnostics.max_images=8"]
HELDOUT = [
    "callbacks.heldout={every_n_steps:4,max_images:2,num_points:300,icp_iterations:2,mean_shape_iterations:5,"
    "own_mean_shape:true}"
]


def _weights(run) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in run.module.model.state_dict().items()}


def test_heldout_rows_and_training_unchanged(synthetic_cache, tmp_path, capsys, caplog):
    plain = build_run(tmp_path / "plain", "callbacks.diagnostics=null")
    fit(plain)
    capsys.readouterr()
    # the code diagnostics (tests/lit/test_diagnostics.py) are watched in the same run
    watched = build_run(tmp_path / "watched", *HELDOUT, *DIAGNOSTICS)
    with caplog.at_level("INFO", logger="unicorn.lit.heldout"):
        fit(watched)
    # progress: a bar while scoring, and a line before each evaluation
    # (the bar's last state is drawn only if scoring outlasts tqdm's refresh interval: check that it is shown)
    assert re.search(r"held-out val: +\d+%\|", capsys.readouterr().err)
    assert re.search(r"held-out val: scoring \d+ images at iteration 4", caplog.text)
    # the callbacks evaluate in eval mode under a forked random state: training is bit-for-bit the same
    a, b = _weights(plain), _weights(watched)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    rows = list(csv.DictReader(open(watched.output_dir / "heldout.csv", encoding="utf-8")))
    # the run's metrics files have their provenance beside them
    (origin,) = json.loads((watched.output_dir / "provenance.json").read_text())
    assert origin["unicorn_version"] and "git_commit" in origin and origin["command"]
    assert [r["step"] for r in rows] == ["0", "4", "8"]
    for r in rows:
        assert 0.0 <= float(r["mask-iou"]) <= 1.0
        assert float(r["chamfer-L1"]) > 0 and float(r["chamfer-L1-ICP"]) > 0
        # the instance-level columns: colour against the mean colour, flips, the mean shape on the same objects
        # (one validation model here: the mean colour is its own, so the baseline is exact and the ratio undefined)
        assert float(r["color-err"]) > 0 and float(r["color-err-mean"]) == 0 and r["color-ratio"] == "nan"
        # one validation image: aligning the canonical frame would fit it exactly, so the pose errors are undefined
        assert r["rot-flip-150"] == r["rot-err-median"] == "nan" and 0.0 <= float(r["shape-win"]) <= 1.0
        assert float(r["chamfer-L1-ICP-mean-shape"]) > 0
        assert float(r["chamfer-L1-ICP-own-mean"]) > 0 and 0.0 <= float(r["shape-win-own"]) <= 1.0
    callback = next(c for c in watched.trainer.callbacks if isinstance(c, HeldOutEvaluation))
    # the mean shape of the run's one category, fitted to its training shapes
    assert callback.mean_shapes is not None and list(callback.mean_shapes) == ["chair"]
    assert callback.mean_shapes["chair"].shape == watched.module.model.template.verts.shape
    # the mean shape is the same at every evaluation: its scores do not move while the model's do
    assert len({r["chamfer-L1-ICP-mean-shape"] for r in rows}) == 1
    assert [row["step"] for row in callback.history] == [0, 4, 8]
    # the untrained model and the trained one are different models: the curve moves
    assert rows[0]["rec-mse"] != rows[-1]["rec-mse"]
    # the last row is the public evaluation of the trained model on the same held-out items, recomputed here:
    # the settings of HELDOUT (the rest HeldOutConfig's defaults), the callback's mean shape as the baseline, and
    # the textures the model was training with at its last iteration (full textures: stage 4, no mean colours)
    model = watched.module.model
    assert not watched.module.constant_mean_textures and int(watched.trainer.global_step) == 8
    data = watched.trainer.datamodule
    heldout = build_eval_dataset(
        "synthetic", str(data.dataset_root()), "val", img_size=model.config["image_size"], categories="chair",
        max_images=2,
    )  # fmt: skip
    settings = dict(
        batch_size=HeldOutConfig.batch_size, num_points=300, icp_iterations=2, own_mean_shape=True,
        shape_points=HeldOutConfig.shape_points, report_samples=0, progress=False,
    )  # fmt: skip
    scores = {
        average: evaluate(
            model, heldout, EvalOptions("shapenet", average_texture=average, **settings), "synthetic",
            shape_baseline=callback.mean_shapes,
        ).mean
        for average in (False, True)
    }  # fmt: skip
    last = rows[-1]
    assert set(scores[False]) - {"group", "n-images"} <= set(last) - {"step"}
    for key, value in scores[False].items():
        if key not in ("group", "n-images"):  # the same computation: equal up to float32 rounding at most
            assert float(last[key]) == pytest.approx(value, rel=1e-7, abs=1e-9, nan_ok=True), key
    # which the mean-colour textures' is not: the colour columns tell the two apart at that tolerance
    assert float(last["color-err"]) != pytest.approx(scores[True]["color-err"], rel=1e-7)
    assert float(last["rec-mse"]) != pytest.approx(scores[True]["rec-mse"], rel=1e-7)

    # code diagnostics: a row every 4 iterations, and no alarm on a healthy start
    rows = list(csv.DictReader(open(watched.output_dir / "diagnostics.csv", encoding="utf-8")))
    assert [r["step"] for r in rows] == ["4", "8"]
    assert {"shape/code-std", "texture/alive-last", "texture/units-last", "pose/azim-spread"} <= set(rows[0])
    diagnostics = next(c for c in watched.trainer.callbacks if isinstance(c, CodeDiagnostics))
    assert not diagnostics.collapsed and not (plain.output_dir / "diagnostics.csv").exists()


def test_csv_keeps_one_row_per_step_and_forgets_what_a_resume_writes_again(tmp_path):
    path = tmp_path / "heldout.csv"
    HeldOutEvaluation._append_csv(path, {"step": 0.0, "mask-iou": 0.1})
    HeldOutEvaluation._append_csv(path, {"step": 4.0, "mask-iou": 0.2})
    HeldOutEvaluation._append_csv(path, {"step": 4.0, "mask-iou": 0.3, "rot-err-median": 9.0})  # a resumed run
    rows = list(csv.DictReader(open(path, encoding="utf-8")))
    assert [(r["step"], r["mask-iou"]) for r in rows] == [("0", "0.1"), ("4", "0.3")]  # steps as integers
    assert rows[1]["rot-err-median"] == "9.0" and rows[0]["rot-err-median"] == ""
    HeldOutEvaluation._append_csv(path, {"step": 8, "mask-iou": 0.4})
    HeldOutEvaluation._append_csv(path, {"step": 4, "mask-iou": 0.5})  # resumed from an earlier checkpoint
    rows = list(csv.DictReader(open(path, encoding="utf-8")))
    assert [(r["step"], r["mask-iou"]) for r in rows] == [("0", "0.1"), ("4", "0.5")]  # 8: abandoned


def test_csv_appends_to_a_file_with_float_steps(tmp_path):
    path = tmp_path / "heldout.csv"
    path.write_text("step,mask-iou\n0.0,0.1\n4.0,0.2\n8.0,0.3\n")  # steps as floats
    HeldOutEvaluation._append_csv(path, {"step": 12, "mask-iou": 0.4})
    assert path.read_text().splitlines() == ["step,mask-iou", "0,0.1", "4,0.2", "8,0.3", "12,0.4"]
    HeldOutEvaluation._append_csv(path, {"step": 8.0, "mask-iou": 0.5})  # a resume, the step as a float
    assert path.read_text().splitlines() == ["step,mask-iou", "0,0.1", "4,0.2", "8,0.5"]
    with pytest.raises(ValueError, match="whole number"):
        HeldOutEvaluation._append_csv(path, {"step": 8.5, "mask-iou": 0.5})


EVALUATE = (
    "evaluate.enabled=true",
    "evaluate.max_images=2",
    "evaluate.num_points=300",
    "evaluate.icp_iterations=2",
    "evaluate.report_samples=2",
    "evaluate.turntable_frames=0",
)


def test_evaluation_after_training_writes_the_report(synthetic_cache, tmp_path):
    run = build_run(tmp_path, *EVALUATE)
    fit(run)
    out = run.output_dir / "eval"
    metrics = json.loads((out / "metrics.json").read_text())
    # provenance: the equivalent unicorn-eval command, and the training command that ran it, kept apart
    assert metrics["command"].startswith(f"unicorn-eval {run.checkpoint_dir / 'last.ckpt'} --split=test")
    level = run.module.model.config["template"]["level"]
    recorded = build_eval_parser().parse_args(shlex.split(metrics["command"])[1:])
    assert recorded.template_level == level  # the trained mesh, whatever the protocol's
    # the command gives the same report: its pictures as large as those written
    with Image.open(next((out / "report").glob("sample*.png"))) as picture:
        assert picture.size == (recorded.view_size, recorded.view_size)
    command = json.loads((run.output_dir / "provenance.json").read_text())[-1]["command"]  # as provenance.json
    assert metrics["produced_by"] == f"{command} (evaluation after training)"
    assert metrics["checkpoint"] == str((run.checkpoint_dir / "last.ckpt").resolve()) and "git_commit" in metrics
    assert (out / "report.png").is_file() and (out / "report.html").is_file()
    text = json.dumps(metrics)
    for key in ("chamfer-L1-ICP", "mask-iou", "rot-err-median"):
        assert key in text


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("callbacks.heldout={split:train}", "callbacks.heldout.split"),
        ("callbacks.heldout={every_n_steps:0}", "callbacks.heldout"),
        ("evaluate.split=everything", "evaluate.split"),
        ("evaluate.max_images=0", r"evaluate\.max_images must be >= 1"),
    ],
)
def test_bad_settings_are_named(tmp_path, override, message):
    from tests.support.training import TINY

    with pytest.raises(ConfigError, match=message):
        validate(compose_config([*TINY, f"paths.output_dir={tmp_path}", override]))


def _set_up(callback: HeldOutEvaluation, root, model) -> None:
    """The callback's set-up at the start of training, on ``root`` (synthetic, every category) with ``model``."""
    data = SimpleNamespace(name="synthetic", root=root, categories=None)
    callback._build_dataset(SimpleNamespace(datamodule=data, callbacks=[]), SimpleNamespace(model=model))


def test_each_category_has_its_own_mean_shape(synth_nmr, caplog):
    model = tiny_model("shapenet")
    callback = HeldOutEvaluation(max_images=2, num_points=300, icp_iterations=2, mean_shape_iterations=5)
    _set_up(callback, synth_nmr, model)
    assert callback.mean_shapes is not None and sorted(callback.mean_shapes) == ["car", "chair"]
    for category, fitted in callback.mean_shapes.items():
        # the oracle: the category's training shapes fitted alone
        clouds = training_point_clouds(synth_nmr, category, HeldOutConfig.mean_shape_models, num_points=300)
        alone = fit_mean_shape(model.template.verts, model.template.faces, clouds, iterations=5)
        assert torch.equal(fitted, alone), category
    # without ICP the mean shape cannot be scored: it is not fitted, and the log says so
    callback = HeldOutEvaluation(max_images=2, num_points=300, icp_iterations=0, mean_shape_iterations=5)
    with caplog.at_level("INFO", logger="unicorn.lit.heldout"):
        _set_up(callback, synth_nmr, model)
    assert callback.mean_shapes is None
    assert "held-out: no mean shape is fitted: it is scored after ICP, and icp_iterations is 0" in caplog.text


def test_bad_arguments():
    with pytest.raises(ValueError, match="split"):
        HeldOutEvaluation(split="train")
    with pytest.raises(ValueError, match=r"every_n_steps must be >= 1, got 0"):
        HeldOutEvaluation(every_n_steps=0)


def test_a_finished_run_resumed_is_evaluated_again_only_where_something_changed(synthetic_cache, tmp_path, caplog):
    fit(build_run(tmp_path, *EVALUATE))
    metrics = tmp_path / "eval" / "metrics.json"
    first = metrics.read_bytes()
    with caplog.at_level("INFO", logger="unicorn.train"):
        fit(build_run(tmp_path, *EVALUATE, "ckpt_path=last"))  # trains nothing: the same model, the same settings
    assert "already holds the evaluation of this iteration's model (8)" in caplog.text
    assert metrics.read_bytes() == first
    metrics.write_text(json.dumps({**json.loads(first), "unicorn_version": "0.0.1"}))  # made by another unicorn
    caplog.clear()
    fit(build_run(tmp_path, *EVALUATE, "ckpt_path=last"))
    assert "already holds" not in caplog.text and json.loads(metrics.read_text())["unicorn_version"] != "0.0.1"
    first = metrics.read_bytes()
    caplog.clear()
    fit(build_run(tmp_path, *EVALUATE, "ckpt_path=last", "evaluate.num_points=400"))  # other settings
    assert (
        "already holds" not in caplog.text
        and json.loads(metrics.read_text())["command"] != json.loads(first)["command"]
    )
    fit(build_run(tmp_path, *EVALUATE, "ckpt_path=last", "evaluate.num_points=400", "trainer.max_steps=9"))
    assert json.loads(metrics.read_text())["step"] == 9  # trained further: evaluated again
