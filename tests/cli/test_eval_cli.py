"""``unicorn-eval`` end to end on a tiny checkpoint and the synthetic fixture set, and its error messages."""

from __future__ import annotations

import csv
import html
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import unicorn
from tests.support.evaluation import referenced_files, synthetic_data, tiny_checkpoint
from unicorn.cli.eval import main

FAST = ["--num-points", "300", "--icp-iterations", "2", "--view-size", "40", "--turntable-frames", "2", "--quiet"]


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthetic_data(tmp_path_factory.mktemp("cli_eval") / "nmr")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_checkpoint(tmp_path_factory.mktemp("cli_eval_ckpt") / "tiny.pt", "shapenet")


def test_eval_command(tmp_path: Path, synth: Path, checkpoint: Path) -> None:
    out = tmp_path / "eval"
    cmd = [sys.executable, "-m", "unicorn.cli.eval", str(checkpoint), "--dataset", "synthetic", "--root", str(synth),
           "--split", "train", "--max-images", "3", "--report-samples", "2", "--device", "cpu", "--out", str(out),
           "--mean-shape", "5", "--own-mean-shape", *FAST]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "chamfer-L1-ICP" in proc.stdout and "\nmean " in proc.stdout  # the table is printed

    with open(out / "metrics.csv", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[:9] == [
        "group", "n-images", "chamfer-L1", "chamfer-L1-ICP", "normal-cos", "normal-cos-ICP", "iou-3d", "iou-3d-ICP",
        "mask-iou",
    ]  # fmt: skip
    assert {"rot-err-median", "rec-mse"} <= set(rows[0]) and [r["group"] for r in rows] == ["chair", "mug", "mean"]
    assert rows[-1]["n-images"] == "3"
    # the instance-level columns, in the table and per image
    instance = {"color-err", "color-err-mean", "chamfer-L1-ICP-mean-shape", "shape-win"}
    instance |= {"chamfer-L1-ICP-own-mean", "shape-win-own"}
    assert instance | {"color-ratio", "rot-flip-150"} <= set(rows[0])
    with open(out / "per_image.csv", encoding="utf-8") as f:
        assert instance | {"rot-err"} <= set(next(csv.DictReader(f)))  # with each image's rotation error
    data = json.loads((out / "metrics.json").read_text())
    assert data["dataset"] == "synthetic" and data["checkpoint_format"] == "plain" and len(data["per_image"]) == 3
    assert data["options"]["num_points"] == 300 and data["protocol"] == "shapenet"
    # provenance: the command, the checkpoint, the package version and the commit, in the JSON and the page
    assert data["command"] == "unicorn-eval " + " ".join(cmd[3:]) and "produced_by" not in data
    assert data["checkpoint"] == str(checkpoint.resolve()) and data["unicorn_version"] == unicorn.__version__
    assert "git_commit" in data and data["torch"] == torch.__version__
    assert html.escape(json.dumps(data["command"])) in (out / "report.html").read_text()
    sources = referenced_files(out / "report.html")
    assert "report.png" in sources and any(s.endswith(".gif") for s in sources)
    assert all((out / s).is_file() for s in sources)


def test_pascal3d_reports_3d_iou(tmp_path: Path, p3d_root: Path, capsys) -> None:
    """``unicorn-eval --dataset p3d_car`` prints and writes the ICP-aligned 3D IoU (no GT pose: no ``iou-3d``)."""
    checkpoint = tiny_checkpoint(tmp_path / "real.pt")
    out = tmp_path / "eval"
    args = [str(checkpoint), "--dataset", "p3d_car", "--root", str(p3d_root), "--device", "cpu", "--out", str(out)]
    assert main([*args, "--report-samples", "0", *FAST]) == 0
    header = next(line for line in capsys.readouterr().out.splitlines() if "chamfer-L1-ICP" in line)
    assert "iou-3d-ICP" in header.split()
    rows = list(csv.DictReader(open(out / "metrics.csv", encoding="utf-8")))
    assert "iou-3d-ICP" in rows[-1] and "iou-3d" not in rows[-1] and rows[-1]["group"] == "mean"
    assert 0 <= float(rows[-1]["iou-3d-ICP"]) <= 1
    per_image = list(csv.DictReader(open(out / "per_image.csv", encoding="utf-8")))
    assert len(per_image) == 2 and all(0 <= float(r["iou-3d-ICP"]) <= 1 for r in per_image)


def test_dataset_of_the_training_run(tmp_path: Path, synth: Path, checkpoint: Path, capsys) -> None:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    os.link(checkpoint, run / "checkpoints" / "last.pt")
    # the synthetic set is in the ShapeNet-NMR format, so it can stand for a shapenet_nmr run
    (run / "config.yaml").write_text(f"dataset:\n  name: shapenet_nmr\n  root: {synth}\n  categories: [mug]\n")
    code = main([str(run / "checkpoints" / "last.pt"), "--split", "train", "--report-samples", "0", *FAST])
    assert code == 0
    out = run / "eval" / "shapenet_nmr_train"  # inside the run directory
    rows = list(csv.DictReader(open(out / "metrics.csv", encoding="utf-8")))
    assert [r["group"] for r in rows] == ["mug", "mean"]  # the run's categories
    assert not (out / "report.html").exists()


def test_synthetic_run_root(tmp_path: Path) -> None:
    from unicorn.cli.eval import _run_root
    from unicorn.data.synthetic.writer import synthetic_dataset_path

    tiny = {"n_models": 3, "image_size": 16, "n_views": 2, "supersample": 1, "n_points": 200}
    run_data = {"name": "synthetic", "root": str(tmp_path), "categories": "car", "synthetic": tiny}
    folder = synthetic_dataset_path("car", "nmr", 3, 0, tmp_path)
    assert _run_root(run_data) == str(folder) and (folder / "synthetic.json").is_file()
    shutil.rmtree(folder)  # the cache cleaned since the run: generated again, as training does
    assert _run_root(run_data) == str(folder) and (folder / "synthetic.json").is_file()
    assert _run_root({"name": "cub_200", "root": "datasets/cub_200"}) == "datasets/cub_200"


def test_a_synthetic_run_root_gone_outside_the_cache_is_named_with_eval_options(tmp_path: Path, checkpoint, capsys):
    # the run generated its data into a folder of the user's (outside the cache), deleted since: unicorn-eval does not
    # create an arbitrary folder, and its hint names what unicorn-eval takes, not unicorn-train's override
    gone = tmp_path / "gone"
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    os.link(checkpoint, run / "checkpoints" / "last.pt")
    (run / "config.yaml").write_text(f"dataset:\n  name: synthetic\n  root: {gone}\n  categories: car\n")
    assert main([str(run / "checkpoints" / "last.pt"), "--report-samples", "0", *FAST]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"unicorn-eval: error: the training run's dataset.root not found at {gone}. Create the folder and unicorn-eval "
        "generates the run's data in it again, or give the generated dataset's folder with --root"
    )
    assert not gone.exists() and not (run / "eval").exists()


def test_a_missing_synthetic_folder_is_named_as_generated_data(tmp_path: Path, checkpoint, capsys) -> None:
    missing = tmp_path / "gone" / "nmr_car_n10_s0_v2"
    assert main([str(checkpoint), "--dataset", "synthetic", "--root", str(missing)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"unicorn-eval: error: generated synthetic dataset not found at {missing}. unicorn-train generates it on "
        "first use in a folder under dataset.root (by default $UNICORN_CACHE/synthetic; $UNICORN_CACHE/synthetic_32px "
        "with +experiment=synthetic), and unicorn-data synth --out DIR with the run's dataset.synthetic settings "
        "generates it again"
    )


def test_a_training_runs_dataset_root_as_root_names_the_datasets_in_it(
    tmp_path: Path, synth: Path, checkpoint: Path, capsys
) -> None:
    """The dataset.root a run records is the parent of the generated datasets: the error names them as --root."""
    parent = tmp_path / "synthetic_32px"  # a scratch cache
    parent.mkdir()
    os.symlink(synth, parent / "nmr_chair+mug_n3_s0_v2")
    out = tmp_path / "eval"
    args = [str(checkpoint), "--dataset", "synthetic", "--split", "train", "--device", "cpu", "--out", str(out)]
    assert main([*args, "--root", str(parent), "--report-samples", "0", *FAST]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"unicorn-eval: error: {parent} is a folder of generated synthetic datasets (as a training run's dataset.root "
        f"is), not one: give one of them as the root: {parent / 'nmr_chair+mug_n3_s0_v2'}\n"
    )
    assert not out.exists()
    assert main([*args, "--root", str(parent / "nmr_chair+mug_n3_s0_v2"), "--report-samples", "0", *FAST]) == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.ckpt", "--dataset", "synthetic", "--root", "."], "checkpoint not found"),
        (["{ckpt}", "--dataset", "synthetic", "--root", "{tmp}/nowhere"], "not found"),
        (["{ckpt}"], "no --dataset given"),
        (["{ckpt}", "--dataset", "cub_200"], "no --root given"),
        (["{ckpt}", "--dataset", "folder", "--root", "{tmp}", "--mean-shape", "5"], "a mean shape needs"),
    ],
)
def test_errors(tmp_path: Path, checkpoint: Path, capsys, args: list[str], message: str) -> None:
    args = [a.format(ckpt=checkpoint, tmp=tmp_path) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-eval: error:") and message in err


@pytest.mark.parametrize("workers", ["0", "-2"])
def test_nn_workers_out_of_range_is_a_usage_error(checkpoint: Path, capsys, workers: str) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([str(checkpoint), "--dataset", "synthetic", "--root", ".", "--nn-workers", workers])
    assert exit_info.value.code == 2
    message = "unicorn-eval: error: --nn-workers must be -1 (all cores) or >= 1"
    assert capsys.readouterr().err.splitlines()[-1] == message


@pytest.mark.parametrize("level", ["8", "-1"])
def test_a_template_level_out_of_range_is_a_usage_error_naming_the_option(tmp_path: Path, capsys, level: str) -> None:
    """Refused while the arguments are parsed (the checkpoint is not read: it does not exist), in the range of the
    model's ``template.level``."""
    from unicorn.model.config import TemplateConfig
    from unicorn.model.ranges import field_range

    assert field_range(TemplateConfig, "level") == (0, 7)
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "missing.ckpt"), "--dataset", "synthetic", "--root", ".", "--template-level", level])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == "unicorn-eval: error: --template-level must be in [0, 7]"


def test_a_malformed_dataset_of_the_checkpoint_is_one_line(tmp_path: Path, checkpoint: Path, capsys) -> None:
    from unicorn.io.serialization import INTEGRITY_KEY

    data = torch.load(checkpoint, weights_only=True)
    data.pop(INTEGRITY_KEY)  # edited by hand
    data["info"] = {"dataset": "xyz"}
    torch.save(data, tmp_path / "odd.pt")
    assert main([str(tmp_path / "odd.pt"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1 and err.startswith("unicorn-eval: error: checkpoint ") and "its 'dataset' is a str" in err
    )


def test_unknown_dataset(checkpoint: Path, capsys) -> None:
    assert main([str(checkpoint), "--dataset", "imagenet", "--root", "."]) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-eval: error: --dataset: unknown dataset 'imagenet'; known: [") and "'cub_200'" in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on machines without CUDA")
def test_cuda_requested_without_cuda(checkpoint: Path, capsys) -> None:
    assert main([str(checkpoint), "--dataset", "synthetic", "--root", ".", "--device", "cuda"]) == 2
    assert "CUDA is not available" in capsys.readouterr().err


def test_a_failure_while_writing_leaves_no_half_written_folder(
    tmp_path: Path, synth: Path, checkpoint: Path, capsys, monkeypatch
) -> None:
    import errno

    import unicorn.evaluation.session as session

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(session, "write_report", full_disk)  # the metrics files are written, then the disk is full
    out = tmp_path / "eval"
    args = [str(checkpoint), "--dataset", "synthetic", "--root", str(synth), "--split", "train", "--max-images", "2"]
    assert main([*args, "--report-samples", "1", "--device", "cpu", "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert err == f"unicorn-eval: error: [Errno 28] No space left on device while writing the output folder {out}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no metrics.csv without its report, no sibling


def test_overwrite_removes_the_report_an_evaluation_without_one_does_not_write(
    tmp_path: Path, synth: Path, checkpoint: Path
) -> None:
    out = tmp_path / "eval"
    args = [str(checkpoint), "--dataset", "synthetic", "--root", str(synth), "--split", "train", "--max-images", "3",
            "--device", "cpu", "--out", str(out), *FAST]  # fmt: skip
    assert main([*args, "--report-samples", "3"]) == 0
    samples = sorted(p.name for p in (out / "report").iterdir())
    assert (out / "report.html").is_file() and len(samples) > 3
    (out / "my_notes.txt").write_text("mine")
    assert main([*args, "--report-samples", "1", "--overwrite"]) == 0  # fewer samples: the others' pictures go
    fewer = sorted(p.name for p in (out / "report").iterdir())
    assert set(fewer) < set(samples) and not any(name.startswith("sample02") for name in fewer)
    assert all((out / name).is_file() for name in referenced_files(out / "report.html"))
    assert main([*args, "--report-samples", "0", "--overwrite"]) == 0  # no report: the earlier one goes
    assert not (out / "report.html").exists() and not (out / "report").exists() and not (out / "report.png").exists()
    assert not (out / "_viewer").exists()
    assert (out / "metrics.csv").is_file() and (out / "my_notes.txt").read_text() == "mine"


def test_overwrite_keeps_the_users_files_in_the_reports_folders(tmp_path: Path, synth: Path, checkpoint: Path) -> None:
    out = tmp_path / "eval"
    args = [str(checkpoint), "--dataset", "synthetic", "--root", str(synth), "--split", "train", "--max-images", "2",
            "--device", "cpu", "--out", str(out), *FAST]  # fmt: skip
    assert main([*args, "--report-samples", "2"]) == 0
    for folder in ("report", "_viewer"):
        (out / folder / "mine.txt").write_text(folder)
    assert main([*args, "--report-samples", "1", "--overwrite"]) == 0
    assert main([*args, "--report-samples", "0", "--overwrite"]) == 0  # the report's own files go, the user's stay
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.parent.name in ("report", "_viewer")) == [
        "_viewer/mine.txt",
        "report/mine.txt",
    ]
    assert (out / "report" / "mine.txt").read_text() == "report" and not (out / "report.html").exists()


def test_a_training_runs_dataset_that_no_plugin_registered_here_is_named(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from unicorn.cli.errors import UsageError
    from unicorn.cli.eval import _target, build_parser

    args = build_parser().parse_args([str(tmp_path / "model.ckpt")])
    info = SimpleNamespace(dataset={"name": "blobs", "root": str(tmp_path)})
    with pytest.raises(
        UsageError, match=r"^the checkpoint's training run read dataset 'blobs', which is not registered"
    ):
        _target(args, info)
    with pytest.raises(UsageError, match=r"needs that plugin here too \(UNICORN_PLUGINS=module\), or give --dataset"):
        _target(args, info)


@pytest.mark.parametrize("dataset", ["cub_200", "p3d_car", "compcars", "lsun", "folder"])
def test_categories_are_refused_for_a_dataset_of_one_category(tmp_path: Path, dataset: str) -> None:
    """--categories would be ignored there (the build reads every item): one line naming the dataset."""
    from types import SimpleNamespace

    from unicorn.cli.errors import UsageError
    from unicorn.cli.eval import _target, build_parser

    parser = build_parser()
    info = SimpleNamespace(dataset=None)
    args = parser.parse_args(
        [str(tmp_path / "m.ckpt"), "--dataset", dataset, "--root", str(tmp_path), "--categories", "car"]
    )
    with pytest.raises(UsageError, match=rf"^--categories picks ShapeNet or synthetic categories; {dataset} has none"):
        _target(args, info)
    tag = ["--tag", "horse"] if dataset == "lsun" else []  # LSUN's category: no run names it here
    args = parser.parse_args([str(tmp_path / "m.ckpt"), "--dataset", dataset, "--root", str(tmp_path), *tag])
    assert _target(args, info).categories is None
    # where categories pick the items, they are taken
    args = parser.parse_args([str(tmp_path / "m.ckpt"), "--dataset", "shapenet_nmr", "--root", str(tmp_path),
                              "--categories", "car,chair"])  # fmt: skip
    assert _target(args, info).categories == ["car", "chair"]


@pytest.mark.parametrize(("text", "names"), [(" car , chair", ["car", "chair"]), ("car,,", ["car"])])
def test_categories_are_read_without_empty_names_or_spaces(tmp_path: Path, text: str, names: list[str]) -> None:
    from types import SimpleNamespace

    from unicorn.cli.eval import _target, build_parser

    args = build_parser().parse_args(
        [str(tmp_path / "m.ckpt"), "--dataset", "shapenet_nmr", "--root", str(tmp_path), "--categories", text]
    )
    assert _target(args, SimpleNamespace(dataset=None)).categories == names


#: no category named: ``--categories "$CATS"`` with the variable unset
NO_CATEGORY = "names no category; give one, or drop --categories"


@pytest.mark.parametrize(
    ("options", "line"),
    [
        (["--dataset", "synthetic", "--categories", ""], f"--categories '' {NO_CATEGORY}"),
        (["--categories", ","], f"--categories ',' {NO_CATEGORY}"),
        (["--dataset", "synthetic", "--tag", "horse"], "--tag is for lsun only (the LSUN category), not synthetic"),
        (
            ["--dataset", "cub_200", "--categories", "car"],
            "--categories picks ShapeNet or synthetic categories; cub_200 has none: drop --categories",
        ),
        (
            ["--dataset", "folder", "--own-mean-shape"],
            "--own-mean-shape: the model's own average shape needs a dataset with ground-truth point clouds, not "
            "folder",
        ),
        (
            ["--dataset", "cub_200", "--mean-shape", "5"],
            "--mean-shape: a mean shape needs a dataset with training point clouds (shapenet protocol), not cub_200",
        ),
    ],
)
def test_options_the_dataset_refuses_are_one_line_before_the_checkpoint_is_read(
    tmp_path: Path, capsys, options: list[str], line: str
) -> None:
    """The checkpoint does not exist: an option refused once it was read would be reported after that error."""
    assert main([str(tmp_path / "missing.ckpt"), "--root", str(tmp_path), "--device", "cpu", *options]) == 2
    assert capsys.readouterr().err == f"unicorn-eval: error: {line}\n"
    assert list(tmp_path.iterdir()) == []


def test_the_cub_protocol_scores_the_level_4_mesh(tmp_path: Path, cub_root: Path, monkeypatch) -> None:
    """UNICORN's keypoint evaluation rebuilds the template at level 4 (2562 vertices); --template-level chooses."""
    import unicorn.io

    real = tiny_checkpoint(tmp_path / "real.pt", "real")
    loaded: list[dict | None] = []
    load = unicorn.io.load_model

    def recording(*args, overrides=None, **kwargs):
        loaded.append(overrides)
        model, info = load(*args, overrides=overrides, **kwargs)
        loaded.append(model.template.verts.shape[0])
        return model, info

    monkeypatch.setattr(unicorn.io, "load_model", recording)
    common = ["--dataset", "cub_200", "--root", str(cub_root), "--max-images", "2", "--report-samples", "0",
              "--device", "cpu", "--num-pairs", "4", *FAST]  # fmt: skip
    assert main([str(real), *common, "--out", str(tmp_path / "a")]) == 0
    assert loaded == [{"template": {"level": 4}}, 2562]
    assert json.loads((tmp_path / "a" / "metrics.json").read_text())["protocol"] == "cub"
    loaded.clear()
    assert main([str(real), *common, "--template-level", "3", "--out", str(tmp_path / "b")]) == 0
    assert loaded == [{"template": {"level": 3}}, 642]


@pytest.mark.parametrize(
    "given, expected",
    [
        ([], (100_000, 100)),  # the full protocol
        (["--fast"], (50_000, 30)),  # UNICORN's validation setting
        (["--fast", "--num-points", "1000"], (1000, 30)),  # an option given wins over --fast's value
        (["--fast", "--icp-iterations", "5"], (50_000, 5)),
        (["--icp-iterations", "0", "--fast", "--num-points", "2000"], (2000, 0)),
        (["--num-points", "3000"], (3000, 100)),
    ],
)
def test_options_given_win_over_fast(given: list[str], expected: tuple[int, int]) -> None:
    from unicorn.cli.eval import _options, build_parser

    options = _options(build_parser().parse_args(["model.ckpt", *given]), "synthetic", average_texture=False)
    assert (options.num_points, options.icp_iterations) == expected


def test_skip_bad_scores_each_readable_image_once(tmp_path: Path, capsys, caplog) -> None:
    """An unreadable image of a folder stops the evaluation unless --skip-bad, which leaves it out with a one-line
    warning; every readable image is scored once (not its neighbour twice, in the unreadable one's place)."""
    import numpy as np
    from PIL import Image

    from unicorn.cli.errors import WARNINGS_LOGGER

    folder = tmp_path / "fold"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(5):
        Image.fromarray(rng.integers(0, 256, (24, 30, 3), dtype=np.uint8)).save(folder / f"img{i}.png")
    (folder / "bad.jpg").write_bytes(b"not a JPEG" * 10)  # first in the listing: its neighbour would stand in
    (folder / "img2.png").write_bytes(b"cut short")  # one among the others
    checkpoint = tiny_checkpoint(tmp_path / "real.pt")
    out = tmp_path / "eval"
    args = [str(checkpoint), "--dataset", "folder", "--root", str(folder), "--device", "cpu", "--out", str(out),
            "--report-samples", "0", "--batch-size", "2", *FAST]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"unicorn-eval: error: cannot read image {folder / 'bad.jpg'}") and err.count("\n") == 1
    caplog.set_level("WARNING", logger=WARNINGS_LOGGER)
    assert main([*args, "--skip-bad"]) == 0
    data = json.loads((out / "metrics.json").read_text())
    assert sorted(row["index"] for row in data["per_image"]) == [1, 2, 4, 5]  # bad.jpg is 0, img2.png 3
    assert data["on_error"] == "skip" and data["command"].endswith(" --skip-bad")
    logged = [r.getMessage() for r in caplog.records if r.name == WARNINGS_LOGGER]
    assert [line.split(": UnidentifiedImageError")[0] for line in logged] == [
        f"SkippedFileWarning: skipping unreadable file: cannot read image {folder / name}"
        for name in ("bad.jpg", "img2.png")
    ]  # one line each, once
