"""benchmarks/quality.py: argument parsing, aggregation over seeds, the table, the bars and the ablation-order line
(no training: the parts that need no model)."""

from __future__ import annotations

import json
import math

import pytest
from omegaconf import OmegaConf

from tests.support.benchmarks import load_script, unload_script
from tests.support.training import compose_config


@pytest.fixture(scope="module")
def quality():
    yield load_script("quality")
    unload_script("quality")


def test_parse_args(quality):
    args = quality.parse_args(["--runs", "full,chairs", "--seeds", "0,2", "--jobs", "2", "a=1"])
    assert args.runs == ["full", "chairs"] and args.seeds == [0, 2] and args.jobs == 2 and args.overrides == ["a=1"]
    assert quality.parse_args([]).seeds == [0] and "chairs" in quality.parse_args([]).runs
    for bad in (["--runs", "nope"], ["--seeds", "a"], ["--seeds", "1,1"], ["--jobs", "0"]):
        with pytest.raises(SystemExit):
            quality.parse_args(bad)


def test_run_layout_and_command(quality, tmp_path):
    args = quality.parse_args(["--runs", "chairs", "--steps", "8", "--out", str(tmp_path), "x=1"])
    run = quality.Run("chairs", 3, tmp_path)
    assert run.dir == (tmp_path / "runs" / "chairs" / "seed3").resolve()
    command = quality.train_command(run, args)
    assert "seed=3" in command and "dataset.categories=chair" in command and "x=1" in command
    assert "trainer.max_steps=8" in command and command[-1] == "ckpt_path=null"
    (run.dir / "checkpoints").mkdir(parents=True)
    (run.dir / "checkpoints" / "last.ckpt").write_bytes(b"")
    assert quality.train_command(run, args)[-1] == "ckpt_path=last"


def test_experiment_option_sets_the_recipe_of_every_variant_but_wild(quality, tmp_path):
    args = quality.parse_args(["--experiment", "synthetic_long", "--out", str(tmp_path)])
    assert quality.train_command(quality.Run("full", 0, tmp_path), args)[3] == "experiment=synthetic_long"
    chairs = quality.train_command(quality.Run("chairs", 0, tmp_path), args)
    assert "experiment=synthetic_long" in chairs and "dataset.categories=chair" in chairs
    assert "experiment=synthetic_wild" in quality.train_command(quality.Run("wild", 0, tmp_path), args)
    assert "experiment=synthetic" in quality.train_command(quality.Run("full", 0, tmp_path), quality.parse_args([]))
    with pytest.raises(SystemExit):
        quality.parse_args(["--experiment", "cub"])


def test_finished_runs_are_reused(quality, tmp_path):
    args = quality.parse_args(["--runs", "full", "--seeds", "0,1", "--out", str(tmp_path)])
    runs = [quality.Run("full", s, tmp_path) for s in (0, 1)]
    for i, run in enumerate(runs):
        run.dir.mkdir(parents=True)
        (run.dir / "done.json").write_text(json.dumps({"minutes": 1.5 + i}))
    assert quality.train_all(runs, args) == {runs[0]: 1.5, runs[1]: 2.5}


def test_threads_per_run(quality, monkeypatch):
    monkeypatch.setattr(quality.os, "cpu_count", lambda: 8)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert [quality.threads_per_run(j) for j in (1, 2, 3, 16)] == [8, 4, 2, 1]
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert quality.threads_per_run(1) == 2


def test_aggregate_and_table(quality):
    mean, std = quality.aggregate({0: {"chamfer-L1-ICP": 0.24, "mask-iou": 0.9}, 1: {"chamfer-L1-ICP": 0.25}})
    assert mean["chamfer-L1-ICP"] == pytest.approx(0.245) and std["chamfer-L1-ICP"] == pytest.approx(0.00707, abs=1e-4)
    assert mean["mask-iou"] == 0.9 and math.isnan(std["mask-iou"])
    table = quality.markdown_table({"full": mean}, {"full": std})
    assert "| full | 0.245 ± 0.007 |" in table and "| 0.900 |" in table
    assert "±" not in quality.markdown_table({"full": mean}, {})


def rows(full_cd: float) -> dict:
    """Means of the car rows: the full model passes every bar but the Chamfer one above 0.24."""
    good = {"color-ratio": 0.2, "rot-acc-30": 0.97, "rot-flip-150": 0.01, "mask-iou": 0.92, "cand-share-min": 0.1}
    return {
        "mean shape (GT pose)": {"chamfer-L1-ICP": 0.3},
        "full": {"chamfer-L1-ICP": full_cd, **good},
        "no-neighbor": {"chamfer-L1-ICP": 0.26, "color-ratio": 0.25, "rot-flip-150": 0.0},
        "no-progressive": {"chamfer-L1-ICP": 0.28, "color-ratio": 0.3, "rot-flip-150": 0.05},
    }


def test_bars(quality):
    assert quality.MEAN_SHAPE_ROW == "mean shape (GT pose)"
    bars = quality.check_bars(rows(0.23))
    assert len(bars) == 6 and all(ok for *_, ok in bars)
    assert bars[0][2] == pytest.approx(0.24)
    bars = quality.check_bars(rows(0.25))
    assert [ok for *_, ok in bars] == [False, True, True, True, True, True]
    assert quality.check_bars({"chairs": {"chamfer-L1-ICP": 0.1}}) == []
    assert quality.baseline_names("chair") == (
        "template, chairs",
        "mean shape (GT pose), chairs",
        "silhouette fit (GT poses, every view), chairs",
    )


def test_silhouette_fit_row_fits_each_object_to_its_own_views(quality, tmp_path, monkeypatch):
    import argparse

    import torch

    import unicorn.evaluation as evaluation
    from unicorn.config import model_preset
    from unicorn.data.synthetic.writer import generate_synthetic_dataset
    from unicorn.model import Unicorn

    root = generate_synthetic_dataset(
        tmp_path, ["car"], "nmr", n_models=6, seed=0, image_size=32, n_views=3, n_points=600, progress=False
    )
    torch.manual_seed(0)
    model = Unicorn(model_preset("shapenet", image_size=32, loss={"perceptual": None})).eval()
    calls, fit = [], evaluation.fit_silhouettes

    def recording(model, masks, R, T, **kw):
        calls.append((masks, R))
        return fit(model, masks, R, T, **kw)

    monkeypatch.setattr(evaluation, "fit_silhouettes", recording)
    args = argparse.Namespace(silhouette_iterations=0, icp_points=500, icp_iterations=2, device="cpu")
    before = quality.silhouette_fit(model, root, args)
    _, every = quality.test_sets(root, 32)
    n_test = len(every.models)
    assert n_test >= 1 and len(calls) == n_test
    for m, (masks, R) in enumerate(calls):  # one call per test object, with all of its views and their cameras
        views = [i for i in range(len(every)) if every.model_view(i)[0] == m]
        assert masks.shape == (3, 1, 32, 32) and len(views) == 3
        assert torch.equal(R, torch.stack([every[i]["R"] for i in views]))
        assert torch.equal(masks, torch.stack([every[i]["mask"] for i in views]))
    args.silhouette_iterations = 100
    after = quality.silhouette_fit(model, root, args)
    assert set(after) == {"chamfer-L1-ICP", "mask-iou"}
    assert after["mask-iou"] > before["mask-iou"] + 0.1 and math.isfinite(after["chamfer-L1-ICP"])


def test_ablation_order(quality):
    line, checks = quality.ablation_order(rows(0.23), {"full": {"chamfer-L1-ICP": 0.01}})
    assert line.startswith("paper's order (full < no-neighbor, full < no-progressive on Chamfer-L1 ICP): holds")
    assert "full 0.230 ± 0.010" in line
    assert [c["holds"] for c in checks] == [True, True, False]  # flip rate: no-neighbor flips less
    assert quality.ablation_order({"full": {}}, {}) is None


def test_categories_table_commands_change_only_the_category_and_the_mode(quality, tmp_path):
    args = quality.parse_args(
        ["--table", "categories", "--experiment", "synthetic_long", "--out", str(tmp_path), "--data-root", "/d"]
    )
    runs = quality.plan(args)
    # cars over three seeds, the others over one
    assert [(r.name, r.seed) for r in runs] == [
        ("car", 0), ("car", 1), ("car", 2), ("chair", 0), ("table", 0), ("lamp", 0), ("mug", 0),
        ("car-wild", 0), ("car-wild", 1), ("car-wild", 2), ("chair-wild", 0),
    ]  # fmt: skip
    commands = {(r.name, r.seed): quality.train_command(r, args) for r in runs}
    recipe = {"experiment=synthetic_long", "dataset.root=/d", "evaluate.enabled=false"}
    for (name, seed), command in commands.items():
        category, mode = quality.CATEGORY_RUNS[name]
        assert command[3] == "experiment=synthetic_long" and recipe <= set(command)
        assert f"dataset.categories={category}" in command and f"dataset.synthetic.mode={mode}" in command
        assert f"seed={seed}" in command and f"hydra.run.dir={(tmp_path / 'runs' / name / f'seed{seed}').resolve()}"
    # the wild mode takes the real family's settings; nothing else differs between two categories' commands
    assert "family=real" in commands[("car-wild", 0)] and "family=real" not in commands[("car", 0)]
    assert "dataset.categories=chair" in commands[("chair-wild", 0)] and "family=real" in commands[("chair-wild", 0)]
    assert set(quality.MODE_OVERRIDES["wild"]) <= set(commands[("car-wild", 0)])
    chair, mug = commands[("chair", 0)], commands[("mug", 0)]
    assert [a for a, b in zip(chair, mug) if a != b] == ["dataset.categories=chair", f"hydra.run.dir={runs[3].dir}"]
    # picking entries and seeds
    args = quality.parse_args(
        ["--table", "categories", "--categories", "mug,car", "--car-seeds", "4", "--seeds", "1,2"]
    )
    assert [(r.name, r.seed) for r in quality.plan(args)] == [("mug", 1), ("mug", 2), ("car", 4)]
    assert "dataset.root" not in " ".join(quality.train_command(quality.plan(args)[0], args))
    for bad in (["--categories", "boat"], ["--car-seeds", "1,1"], ["--threads", "0"]):
        with pytest.raises(SystemExit):
            quality.parse_args(["--table", "categories", *bad])
    # the ablations table is unchanged by the categories options
    assert [r.name for r in quality.plan(quality.parse_args(["--runs", "full,wild"]))] == ["full", "wild"]


def test_dry_run_prints_one_command_per_run(quality, tmp_path, capsys):
    argv = ["--table", "categories", "--categories", "chair,car-wild", "--jobs", "2", "--threads", "1"]
    assert quality.main([*argv, "--car-seeds", "0", "--out", str(tmp_path / "q"), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("# 2 training runs, up to 2 at once, 1 thread(s) each")
    assert lines[1].startswith("OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 python -m unicorn.cli.train experiment=synthetic")
    assert "dataset.categories=chair" in lines[1] and "dataset.synthetic.mode=wild family=real" in lines[2]
    assert not (tmp_path / "q").exists()  # nothing trained, nothing written


def test_categories_table_and_bars(quality):
    rows = {
        "silhouette fit (GT poses, every view), car": {"chamfer-L1-ICP": 0.2, "mask-iou": 0.95, "shape-top3": 0.9},
        "car": {
            "shape-top3": 0.62, "shape-top3-floor": 0.3, "chamfer-L1-ICP": 0.21, "color-ratio": 0.3,
            "color-ratio-overlap": 0.25, "rot-acc-30": 0.96, "rot-flip-150": 0.01, "rot-acc-30-any": 0.99,
            "mask-iou": 0.91, "train-minutes": 9.5,
        },
        "chair": {
            "shape-top3": 0.4, "shape-top3-floor": 0.25, "color-ratio": 0.4, "rot-acc-30": 0.95, "mask-iou": 0.85,
        },
    }  # fmt: skip
    stds = {"car": {"shape-top3": 0.05, "chamfer-L1-ICP": 0.01}}
    table = quality.markdown_table(rows, stds, quality.CATEGORY_COLUMNS)
    lines = table.splitlines()
    assert lines[0] == (
        "| model | shape top-3 | top-3 floor (scale only) | Chamfer-L1 ICP | colour ratio | colour ratio, overlap | "
        "rot. acc. 30 deg | flipped (> 150 deg) | some candidate within 30 deg | mask IoU | train (min) |"
    )
    silhouette_row = "| silhouette fit (GT poses, every view), car | 0.90 | – | 0.200 | – | – | – | – | – | 0.950 | – |"
    assert lines[2] == silhouette_row
    car_row = "| car | 0.62 ± 0.05 | 0.30 | 0.210 ± 0.010 | 0.30 | 0.25 | 0.960 | 0.010 | 0.990 | 0.910 | 9.5 |"
    assert lines[3] == car_row
    bars = {bar: ok for bar, _, _, ok in quality.check_category_bars(rows)}
    assert bars["car: shape-top3 >= 0.6"] and bars["car: shape-top3 >= 2.0 x shape-top3-floor"]
    assert bars["car: chamfer-L1-ICP <= 1.1 x the silhouette fit's"]  # 0.21 <= 0.22
    assert not bars["chair: shape-top3 >= 2.0 x shape-top3-floor"]  # 0.4 < 0.5
    assert bars["chair: mask-iou >= 0.8"] and len(bars) == 7 + 4
    # without its silhouette row the relative Chamfer bar is left out; a missing metric is missed
    bars = quality.check_category_bars({"car": {"shape-top3": 0.7}})
    assert (
        not any("silhouette" in b for b, *_ in bars) and not dict((b, ok) for b, *_, ok in bars)["car: mask-iou >= 0.9"]
    )


def test_prepare_data_generates_each_dataset_once_with_the_runs_settings(quality, tmp_path, monkeypatch):
    import unicorn.data

    calls = []
    monkeypatch.setattr(unicorn.data, "prepare_dataset", lambda *a: calls.append(a) or tmp_path)
    argv = ["--table", "categories", "--categories", "car,mug,car-wild", "--car-seeds", "0,1", "--data-root", "/d"]
    args = quality.parse_args([*argv, "--out", str(tmp_path)])
    quality.prepare_data(quality.plan(args), args)
    assert [(name, root, category, synthetic["mode"]) for name, root, category, synthetic in calls] == [
        ("synthetic", "/d", "car", "nmr"),
        ("synthetic", "/d", "mug", "nmr"),
        ("synthetic", "/d", "car", "wild"),
    ]


def test_categories_table_wild_entry_is_the_shipped_wild_experiment(quality, tmp_path):
    # with the main job's recipe, the wild entry trains what `unicorn-train experiment=synthetic_wild` trains
    args = quality.parse_args(["--table", "categories", "--categories", "car-wild", "--experiment", "synthetic"])
    overrides = quality.recipe("car-wild", args)
    assert overrides[0] == "experiment=synthetic"
    common = [f"paths.output_dir={tmp_path}", "task_name=synthetic_wild"]
    table = OmegaConf.to_yaml(compose_config([*overrides, *common]))
    assert table == OmegaConf.to_yaml(compose_config(["experiment=synthetic_wild", *common]))


def test_categories_table_trains_twice_as_long_and_holds_the_wild_scale_through_its_stage_1(quality):
    args = quality.parse_args(["--table", "categories"])
    assert quality.parse_args([]).experiment == "synthetic" and args.experiment == "synthetic_9600"
    main, table = compose_config(["experiment=synthetic"]), compose_config(quality.recipe("car", args))
    assert table.trainer.max_steps == 2 * main.trainer.max_steps
    assert table.optim.lr_drop_step == 2 * main.optim.lr_drop_step
    assert list(table.schedule.milestones) == [2 * m for m in main.schedule.milestones]
    wild = compose_config(quality.recipe("car-wild", args))
    assert wild.schedule.curriculum.scale == wild.schedule.milestones[0] == 3200
    assert table.schedule.curriculum.scale == main.schedule.curriculum.scale == 150  # NMR views: from iteration 150


def test_wild_bars(quality):
    rows = {
        "car-wild": {"rot-acc-30": 0.81, "rot-flip-150": 0.06, "mask-iou": 0.86, "color-ratio": 0.5},
        "chair-wild": {"rot-acc-30": 0.69, "mask-iou": 0.8},
    }
    bars = {bar: ok for bar, _, _, ok in quality.check_category_bars(rows)}
    assert bars == {
        "car-wild: rot-acc-30 >= 0.8": True,
        "car-wild: rot-flip-150 <= 0.05": False,
        "car-wild: mask-iou >= 0.85": True,
        "car-wild: color-ratio <= 0.6": True,
        "chair-wild: rot-acc-30 >= 0.7": False,
        "chair-wild: mask-iou >= 0.75": True,
    }
