"""``unicorn-reconstruct`` end to end on a tiny checkpoint and fixture images, and its error messages."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

import unicorn
from tests.support.checkpoints import reference_state
from tests.support.datasets import bomb_png
from tests.support.evaluation import TEXTURE_SIZE, referenced_files, tiny_checkpoint, tiny_model, write_inputs
from tests.support.signals import SignalAtCall
from unicorn.cli.reconstruct import main
from unicorn.data.images import MAX_IMAGE_BYTES_ENV, MAX_IMAGE_PIXELS_ENV
from unicorn.io import export_prediction, load_input, load_model, save_model

FAST = ["--view-size", "48", "--turntable-frames", "3", "--strip-views", "3", "--quiet", "--device", "cpu"]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_checkpoint(tmp_path_factory.mktemp("cli_rec_ckpt") / "tiny.pt", "real")


@pytest.fixture(scope="module")
def varied_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny checkpoint whose mesh, scale and pose differ from image to image (random output layers; the plain
    tiny model predicts the same ones for every image)."""
    model = tiny_model("real")
    model.set_active_dims(shape=model.shape.code_dim)
    layers = [(model.shape.regressor[-1], 1.0), (model.shape.field.mlp[-1], 0.05), (model.scale.regressor[-1], 1.0)]
    layers += [(mlp[-1], 1.0) for mlp in (*model.pose.rot_regressors, *model.pose.T_regressors)]
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for layer, std in layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen) * std)
    return save_model(model, tmp_path_factory.mktemp("cli_rec_varied") / "varied.pt")


@pytest.fixture
def inputs(tmp_path: Path) -> Path:
    write_inputs(tmp_path / "inputs")
    return tmp_path / "inputs"


def test_console_scripts_are_installed() -> None:
    scripts = {ep.name: ep.value for ep in entry_points(group="console_scripts")}
    assert scripts.get("unicorn-reconstruct") == "unicorn.cli.reconstruct:main"
    assert scripts.get("unicorn-eval") == "unicorn.cli.eval:main"


def test_reconstruct_command(tmp_path: Path, varied_checkpoint: Path, inputs: Path) -> None:
    """The command's files, each image's against the model run here on that image alone."""
    checkpoint = varied_checkpoint
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "unicorn.cli.reconstruct", str(checkpoint), str(inputs), "--out", str(out), *FAST]
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "2 images reconstructed" in proc.stdout

    model, info = load_model(checkpoint)
    files = {"cutout": inputs / "cutout.png", "photo": inputs / "photo.jpg"}
    poses = {}
    for name in ("cutout", "photo"):
        folder = out / name
        # each image's files are that image's prediction: the model run here on it alone, framed as the command does
        image = load_input(files[name], model.config["image_size"]).image[None]
        with torch.no_grad():
            pred = model.predict(image, average_texture=info.average_texture)
        expected = export_prediction(model, pred, 0)
        for file in ("input.png", "reconstruction.png", "mask.png", "turntable.gif", "turntable.png", "pose.json",
                     "mesh.obj", "mesh.mtl", "mesh.png", "mesh.glb"):  # fmt: skip
            assert (folder / file).is_file(), file
        assert Image.open(folder / "input.png").size == (32, 32)
        assert Image.open(folder / "reconstruction.png").size == (48, 48)
        assert Image.open(folder / "turntable.png").size == (3 * 48, 48)
        assert Image.open(folder / "turntable.gif").n_frames == 3
        obj = trimesh.load(folder / "mesh.obj", force="mesh", process=False)
        glb = trimesh.load(folder / "mesh.glb", force="mesh", process=False)
        for mesh in (obj, glb):
            assert mesh.vertices.shape == expected.vertices.shape and mesh.faces.shape == expected.faces.shape
            assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
        assert obj.visual.material.image.size == (TEXTURE_SIZE, TEXTURE_SIZE)
        assert glb.visual.material.baseColorTexture.size == (TEXTURE_SIZE, TEXTURE_SIZE)
        # the OBJ's positions, one per template vertex in its order, are the prediction's object-frame vertices with
        # the anisotropic scale applied (docs/reconstruct.md: scale * canonical; this model's scale is not 1)
        assert (pred.scale[0] - 1).abs().max() > 0.05
        lines = (folder / "mesh.obj").read_text().splitlines()
        positions = torch.tensor([[float(x) for x in line.split()[1:4]] for line in lines if line.startswith("v ")])
        corners = [[int(c.split("/")[0]) - 1 for c in line.split()[1:]] for line in lines if line.startswith("f ")]
        scaled = pred.canonical_verts[0] * pred.scale[0]
        torch.testing.assert_close(positions, scaled, atol=1e-5, rtol=0)
        assert torch.equal(torch.tensor(corners), model.template.faces.cpu())
        pose = json.loads((folder / "pose.json").read_text())
        R = torch.tensor(pose["R"])
        torch.testing.assert_close(R @ R.T, torch.eye(3), atol=1e-5, rtol=0)
        assert len(pose["T"]) == 3 and len(pose["candidate_probabilities"]) == 6
        torch.testing.assert_close(R, pred.R[0], atol=1e-5, rtol=0)
        torch.testing.assert_close(torch.tensor(pose["T"]), pred.T[0], atol=1e-5, rtol=0)
        assert pose["scale"] == pytest.approx(pred.scale[0].tolist(), abs=1e-5)
        assert pose["candidate_probabilities"] == pytest.approx(pred.poses.probs[:, 0].tolist(), abs=1e-5)
        poses[name] = R, torch.tensor(pose["T"]), positions
    # two different inputs, two different poses and meshes (so the comparisons above tell the images apart)
    assert (poses["cutout"][2] - poses["photo"][2]).abs().max() > 1e-2
    assert (poses["cutout"][0] - poses["photo"][0]).abs().max() > 1e-2
    assert (poses["cutout"][1] - poses["photo"][1]).abs().max() > 1e-2
    # the photo (70 x 40) fitted into 32 x 32: 32 x 18 pixels, 7 rows of padding above: its frame in photo pixels
    frame = json.loads((out / "photo" / "pose.json").read_text())["frame"]
    assert frame == pytest.approx({"x": 0.0, "y": -7 * 40 / 18, "width": 70.0, "height": 32 * 40 / 18})
    saved = json.loads((out / "reconstructions.json").read_text())
    records = saved["images"]
    assert [r["name"] for r in records] == ["cutout", "photo"]
    # provenance: this command (not the test runner's), the checkpoint, the package version, the commit
    origin = saved["provenance"]
    assert origin["command"].startswith(f"unicorn-reconstruct {checkpoint} {inputs} --out {out}")
    assert origin["checkpoint"] == str(checkpoint.resolve()) and origin["unicorn_version"] == unicorn.__version__
    assert "git_commit" in origin and json.loads((out / "photo" / "pose.json").read_text())["provenance"] == origin
    assert origin["command"] in (out / "index.html").read_text()
    assert records[0]["cropped_from_alpha_or_box"] and not records[1]["cropped_from_alpha_or_box"]
    for record in records:  # every file of an image's folder is listed (a copy of the listed files is whole)
        assert sorted(record["files"].values()) == sorted(p.name for p in (out / record["folder"]).iterdir())
    assert (out / "overview.png").is_file()
    assert all((out / s).is_file() for s in referenced_files(out / "index.html"))


def test_released_checkpoint(tmp_path: Path, inputs: Path) -> None:
    torch.save({"epoch": 2, "model_kwargs": {}, "model_state": reference_state()}, tmp_path / "model.pkl")
    code = main([str(tmp_path / "model.pkl"), str(inputs / "photo.jpg"), "--out", str(tmp_path / "out"),
                 *FAST, "--turntable-frames", "0"])  # fmt: skip
    assert code == 0
    assert (tmp_path / "out" / "photo" / "mesh.glb").is_file()
    assert not (tmp_path / "out" / "photo" / "turntable.gif").exists()


def _skipped(caplog: pytest.LogCaptureFixture) -> list[str]:
    """The lines ``--skip-bad`` logged (:func:`unicorn.cli.errors.log_warnings`), one per skipped input."""
    from unicorn.cli.errors import WARNINGS_LOGGER

    return [r.getMessage() for r in caplog.records if r.name == WARNINGS_LOGGER]


def test_bad_image_skipped_on_request(tmp_path: Path, checkpoint: Path, inputs: Path, capsys, caplog) -> None:
    (inputs / "broken.png").write_bytes(b"not a png")
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "a"), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-reconstruct: error: cannot read image") and "broken.png" in err
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "b"), "--skip-bad", *FAST]) == 0
    assert len(_skipped(caplog)) == 1 and "broken.png" in _skipped(caplog)[0]
    folders = sorted(p.name for p in (tmp_path / "b").iterdir() if p.is_dir())
    assert folders == ["_viewer", "cutout", "photo"]


def test_a_fully_transparent_image_is_a_bad_input_and_its_skip_one_line(
    tmp_path: Path, checkpoint: Path, inputs: Path, capsys, caplog
) -> None:
    Image.new("RGBA", (20, 16), (255, 0, 0, 0)).save(inputs / "clear.png")
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "a"), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "clear.png: it has no opaque pixel" in err
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "b"), "--skip-bad", *FAST]) == 0
    warned = _skipped(caplog)
    assert len(warned) == 1 and warned[0].startswith("SkippedInputWarning: skipping cannot read image")
    assert "clear.png" in warned[0] and "\n" not in warned[0]
    assert "RuntimeWarning" not in capsys.readouterr().err  # not printed as Python prints warnings
    assert sorted(p.name for p in (tmp_path / "b").iterdir() if p.is_dir()) == ["_viewer", "cutout", "photo"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["{tmp}/missing.ckpt", "{inputs}"], "checkpoint not found"),
        (["{ckpt}", "{tmp}/empty"], "no images"),
        (["{ckpt}", "{tmp}/nothing.png"], "input not found"),
        (["{ckpt}", "{inputs}", "--bbox", "0,0,10,10"], "--bbox needs exactly one input image"),
        (["{inputs}/photo.jpg", "{inputs}"], "cannot read checkpoint"),
    ],
)
def test_errors(tmp_path: Path, checkpoint: Path, inputs: Path, capsys, args: list[str], message: str) -> None:
    (tmp_path / "empty").mkdir()
    args = [a.format(ckpt=checkpoint, tmp=tmp_path, inputs=inputs) for a in args]
    assert main([*args, "--out", str(tmp_path / "out"), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-reconstruct: error:") and message in err


@pytest.mark.parametrize(
    "args, line",
    [
        (["--template-level", "9"], "--template-level must be in [0, 7]"),
        (["--refine", "-1"], "--refine must be >= 0"),
        (["--turntable-frames", "-2"], "--turntable-frames must be >= 0"),
        (["--bbox", "1,2,3"], "argument --bbox: must be four numbers x1,y1,x2,y2, got '1,2,3'"),
    ],
)
def test_a_bad_option_is_a_usage_error_naming_it_once(tmp_path: Path, capsys, args: list[str], line: str) -> None:
    """Refused while the arguments are read: the checkpoint and the image (missing here) are not read."""
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "missing.ckpt"), str(tmp_path / "photo.jpg"), *args])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == f"unicorn-reconstruct: error: {line}"


def test_decompression_bomb_is_skipped_or_one_line(
    tmp_path: Path, checkpoint: Path, inputs: Path, capsys, caplog, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, "")  # --max-image-pixels sets it for the process: restored after
    bomb_png(inputs / "bomb.png")
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "a"), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bomb.png" in err and "exceeds the limit" in err
    assert not (tmp_path / "a").exists()
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "b"), "--skip-bad", *FAST]) == 0
    assert len(_skipped(caplog)) == 1 and "bomb.png" in _skipped(caplog)[0]
    assert sorted(p.name for p in (tmp_path / "b").iterdir() if p.is_dir()) == ["_viewer", "cutout", "photo"]
    # a limit the user lowers applies too
    assert main([str(checkpoint), str(inputs / "photo.jpg"), "--out", str(tmp_path / "c"),
                 "--max-image-pixels", "100", *FAST]) == 2  # fmt: skip
    assert "exceeds the limit of 100" in capsys.readouterr().err


def test_image_byte_limit_option(tmp_path: Path, checkpoint: Path, inputs: Path, capsys, monkeypatch) -> None:
    monkeypatch.setenv(MAX_IMAGE_BYTES_ENV, "")  # --max-image-bytes sets it for the process: restored after
    assert main([str(checkpoint), str(inputs / "photo.jpg"), "--out", str(tmp_path / "a"),
                 "--max-image-bytes", "100", *FAST]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "photo.jpg" in err and "over the limit of 100" in err
    with pytest.raises(SystemExit):
        main([str(checkpoint), str(inputs), "--max-image-bytes", "-1"])
    assert "--max-image-bytes must be >= 0" in capsys.readouterr().err


def test_non_empty_out_needs_overwrite(tmp_path: Path, checkpoint: Path, inputs: Path, capsys) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "index.html").write_text("the user's own page")
    assert main([str(checkpoint), str(inputs / "photo.jpg"), "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--overwrite" in err and str(out) in err
    assert [p.name for p in out.iterdir()] == ["index.html"]
    assert (out / "index.html").read_text() == "the user's own page"
    assert main([str(checkpoint), str(inputs / "photo.jpg"), "--out", str(out), "--overwrite", *FAST]) == 0
    assert (out / "photo" / "mesh.glb").is_file() and "photo" in (out / "index.html").read_text()


def test_an_input_folder_that_is_the_output_folder_is_refused_saying_why(
    tmp_path: Path, checkpoint: Path, inputs: Path, capsys
) -> None:
    """--out the photo folder itself: its images are left out as outputs, and the error says so (not just "no images"
    in a folder the user sees images in); nothing is written there."""
    before = sorted(p.name for p in inputs.iterdir())
    assert main([str(checkpoint), str(inputs), "--out", str(inputs), "--overwrite", *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"in folder {inputs} other than outputs, which are not read" in err
    assert sorted(p.name for p in inputs.iterdir()) == before


def test_input_names_never_collide_with_the_outputs(tmp_path: Path, checkpoint: Path, inputs: Path) -> None:
    for name in ("index.html.png", "overview.png.png", "reconstructions.json.png", "Index.HTML.jpg"):
        (inputs / name).write_bytes((inputs / "photo.jpg").read_bytes())
    out = tmp_path / "out"
    assert main([str(checkpoint), str(inputs), "--out", str(out), *FAST]) == 0
    for name in ("index.html", "overview.png", "reconstructions.json"):
        assert (out / name).is_file()
    records = json.loads((out / "reconstructions.json").read_text())["images"]
    assert len(records) == 6 and all((out / r["name"] / "mesh.glb").is_file() for r in records)
    assert all(r["folder"] == r["name"] for r in records)  # within --out (the files were written elsewhere first)
    names = [r["name"].lower() for r in records]
    assert len(set(names)) == 6 and not set(names) & {"index.html", "overview.png", "reconstructions.json"}
    assert {"index.html_1", "overview.png_1", "reconstructions.json_1"} <= set(names)


def test_names_in_any_script_are_kept_and_linked(tmp_path: Path, checkpoint: Path, inputs: Path) -> None:
    photo = inputs / "車の写真 #1.jpg"
    photo.write_bytes((inputs / "photo.jpg").read_bytes())
    out = tmp_path / "out"
    assert main([str(checkpoint), str(photo), "--out", str(out), *FAST]) == 0
    assert (out / "車の写真_1" / "mesh.glb").is_file()
    page = (out / "index.html").read_text(encoding="utf-8")
    assert "%E8%BB%8A" in page  # the links are percent-encoded UTF-8
    assert all((out / s).is_file() for s in referenced_files(out / "index.html"))


def test_refine_writes_the_refined_result_beside_the_network(tmp_path: Path, checkpoint: Path, inputs: Path) -> None:
    photo = str(inputs / "cutout.png")  # an image whose objective the refinement lowers (the photo's it does not)
    assert main([str(checkpoint), photo, "--out", str(tmp_path / "plain"), *FAST]) == 0
    refined_args = ["--refine", "6"]
    assert main([str(checkpoint), photo, "--out", str(tmp_path / "refined"), *refined_args, *FAST]) == 0
    plain, refined = tmp_path / "plain" / "cutout", tmp_path / "refined" / "cutout"
    # the network's own pictures beside the refined ones, identical to an unrefined run's
    for name in ("reconstruction_network.png", "turntable_network.png"):
        assert (refined / name).is_file() and not (plain / name).exists()
    same = {"reconstruction_network.png": "reconstruction.png", "turntable_network.png": "turntable.png"}
    for ours, theirs in same.items():
        assert Image.open(refined / ours).tobytes() == Image.open(plain / theirs).tobytes(), ours
    # the exports carry the refined result: by default the appearance and the outline; the pose is kept
    for name in ("mesh.png", "mesh.glb", "mesh.obj", "reconstruction.png"):
        assert (refined / name).read_bytes() != (plain / name).read_bytes(), name
    poses = [json.loads((folder / "pose.json").read_text()) for folder in (plain, refined)]
    assert poses[0]["R"] == poses[1]["R"] and poses[0]["T"] == poses[1]["T"]
    record = json.loads((tmp_path / "refined" / "reconstructions.json").read_text())["images"][0]
    assert record["refinement"]["steps"] == 6
    assert sorted(record["files"].values()) == sorted(p.name for p in refined.iterdir())  # the network's too
    # the objective is reported, that of the result written (tested on the library, tests/objectives/test_refine.py)
    assert all(math.isfinite(record["refinement"][k]) for k in ("objective_refined", "objective_network"))
    assert record["refinement"]["objective_refined"] < record["refinement"]["objective_network"]
    wide, narrow = Image.open(tmp_path / "refined" / "overview.png"), Image.open(tmp_path / "plain" / "overview.png")
    assert wide.size[0] > narrow.size[0] and wide.size[1] == narrow.size[1]
    assert "reconstruction_network.png" in (tmp_path / "refined" / "index.html").read_text()


def test_refine_parts_are_checked(tmp_path: Path, checkpoint: Path, inputs: Path, capsys) -> None:
    args = [str(checkpoint), str(inputs / "photo.jpg"), "--out", str(tmp_path / "out"), *FAST, "--refine", "2"]
    assert main([*args, "--refine-parts", "codes,colour"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("unicorn-reconstruct: error: --refine-parts") and "colour" in err
    assert main([*args, "--refine-parts", "texture"]) == 0
    with pytest.raises(SystemExit):
        main([str(checkpoint), str(inputs), "--out", str(tmp_path / "neg"), *FAST, "--refine", "-1"])
    assert "--refine must be >= 0" in capsys.readouterr().err


def test_a_full_disk_part_way_is_one_line_and_leaves_out_as_it_was(
    tmp_path: Path, checkpoint: Path, inputs: Path, capsys, monkeypatch
) -> None:
    import errno
    import importlib

    rec = importlib.import_module("unicorn.evaluation.reconstruct")  # the package exports a function of that name

    written = rec._write_one

    def second_fails(*args, **kwargs):
        if second_fails.calls == 1:
            raise OSError(errno.ENOSPC, "No space left on device")  # a write() on a full disk names no file
        second_fails.calls += 1
        return written(*args, **kwargs)

    second_fails.calls = 0
    monkeypatch.setattr(rec, "_write_one", second_fails)
    out = tmp_path / "out"
    assert main([str(checkpoint), str(inputs), "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert (
        err == f"unicorn-reconstruct: error: [Errno 28] No space left on device while writing the output folder {out}\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inputs"]  # no out, no half-written sibling
    # an existing folder (--overwrite) keeps its files untouched
    out.mkdir()
    (out / "index.html").write_text("the user's own page")
    second_fails.calls = 0
    assert main([str(checkpoint), str(inputs), "--out", str(out), "--overwrite", *FAST]) == 2
    assert [p.name for p in out.iterdir()] == ["index.html"] and (
        out / "index.html"
    ).read_text() == "the user's own page"


def test_a_signal_part_way_stops_at_once_and_leaves_out_as_it_was(
    tmp_path: Path, checkpoint: Path, inputs: Path, capsys, monkeypatch
) -> None:
    import importlib
    import signal

    rec = importlib.import_module("unicorn.evaluation.reconstruct")  # the package exports a function of that name
    signalled = SignalAtCall(monkeypatch, rec, "_write_one", at=2)  # SIGTERM once the first image's files are written
    out = tmp_path / "out"
    out.mkdir()
    (out / "index.html").write_text("the user's own page")
    assert main([str(checkpoint), str(inputs), "--out", str(out), "--overwrite", *FAST]) == 128 + signal.SIGTERM
    assert capsys.readouterr().err == "unicorn-reconstruct: stopped by SIGTERM\n"
    assert signalled.calls == 2  # stopped at the second image
    assert [p.name for p in out.iterdir()] == ["index.html"] and (
        out / "index.html"
    ).read_text() == "the user's own page"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inputs", "out"]  # no half-written sibling


def test_an_output_folder_another_run_fills_meanwhile_is_not_mixed_into(
    tmp_path: Path, checkpoint: Path, inputs: Path, monkeypatch, capsys
) -> None:
    import importlib

    rec = importlib.import_module("unicorn.evaluation.reconstruct")  # the package exports a function of that name
    write_one = rec._write_one
    out = tmp_path / "out"

    def another_run_finishes_first(*args, **kwargs):
        if not out.exists():  # two runs started into the same new folder: the other one moves its files first
            out.mkdir()
            (out / "reconstructions.json").write_text("the other run's")
        return write_one(*args, **kwargs)

    monkeypatch.setattr(rec, "_write_one", another_run_finishes_first)
    assert main([str(checkpoint), str(inputs), "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"unicorn-reconstruct: error: the output folder {out} was written by another command")
    assert [p.name for p in out.iterdir()] == ["reconstructions.json"]
    assert (out / "reconstructions.json").read_text() == "the other run's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inputs", "out"]  # no temporary folder left
    assert main([str(checkpoint), str(inputs), "--out", str(out), "--overwrite", *FAST]) == 0  # asked: merged


@pytest.mark.parametrize(
    "argv",
    [["--bbox", "-5,10,200,300"], ["--bbox=-5,10,200,300"], ["--bbox", "-.5,10,200,300"]],
    ids=["spaced", "joined", "fraction"],
)
def test_a_box_starting_left_of_the_image_is_a_value_not_an_option(argv: list[str]) -> None:
    from unicorn.cli.reconstruct import _negative_boxes, build_parser

    args = build_parser().parse_args(_negative_boxes(["model.pkl", "photo.jpg", *argv, "--out", "out"]))
    assert args.bbox[0] < 0 and list(args.bbox[1:]) == [10, 200, 300] and args.out == Path("out")
    assert _negative_boxes(["m.pkl", "--", "--bbox", "-5,1,2,3"]) == ["m.pkl", "--", "--bbox", "-5,1,2,3"]


def test_outputs_inside_an_input_folder_are_not_read_back(tmp_path: Path, checkpoint: Path, inputs: Path) -> None:
    assert main([str(checkpoint), str(inputs), "--out", str(inputs / "rec"), *FAST]) == 0
    # a second run into another folder inside the inputs: the first run's outputs are not photos
    assert main([str(checkpoint), str(inputs), "--out", str(inputs / "rec2"), *FAST]) == 0
    for out in ("rec", "rec2"):
        records = json.loads((inputs / out / "reconstructions.json").read_text())["images"]
        assert sorted(r["name"] for r in records) == ["cutout", "photo"], out
        assert all(Path(r["source"]).is_absolute() for r in records)
    # and a run into the same folder again, overwriting it
    assert main([str(checkpoint), str(inputs), "--out", str(inputs / "rec"), "--overwrite", *FAST]) == 0
    assert len(json.loads((inputs / "rec" / "reconstructions.json").read_text())["images"]) == 2


def test_hidden_files_are_left_out_and_names_go_to_the_readable_images(
    tmp_path: Path, checkpoint: Path, inputs: Path, caplog
) -> None:
    (inputs / "._photo.jpg").write_bytes(b"\x00\x05\x16\x07 a Mac's resource file")
    (inputs / ".thumbnails").mkdir()
    (inputs / ".thumbnails" / "thumb.jpg").write_bytes((inputs / "photo.jpg").read_bytes())
    (inputs / "a").mkdir()
    (inputs / "a" / "photo.png").write_bytes(b"not a png")  # unreadable, skipped: it takes no name
    Image.open(inputs / "photo.jpg").save(inputs / "a" / "still.gif")  # a GIF in a folder is an image
    out = tmp_path / "out"
    args = [str(checkpoint), str(inputs), str(inputs / "photo.jpg"), "--out", str(out), "--skip-bad", *FAST]
    assert main(args) == 0  # photo.jpg named twice: read once
    assert len(_skipped(caplog)) == 1 and "a/photo.png" in _skipped(caplog)[0]
    records = json.loads((out / "reconstructions.json").read_text())["images"]
    assert sorted(r["name"] for r in records) == ["cutout", "photo", "still"]


def test_overwrite_removes_the_optional_files_the_new_run_does_not_make(
    tmp_path: Path, checkpoint: Path, inputs: Path
) -> None:
    out, photo = tmp_path / "out", str(inputs / "photo.jpg")
    assert main([str(checkpoint), photo, "--out", str(out), "--refine", "2", *FAST]) == 0
    (out / "photo" / "my_notes.txt").write_text("mine")
    made = {p.name for p in (out / "photo").iterdir()}
    assert {"turntable.gif", "reconstruction_network.png", "turntable_network.png"} <= made
    assert main([str(checkpoint), photo, "--out", str(out), "--overwrite", *FAST, "--turntable-frames", "0"]) == 0
    left = {p.name for p in (out / "photo").iterdir()}
    assert left == made - {"turntable.gif", "reconstruction_network.png", "turntable_network.png"}
    assert (out / "photo" / "my_notes.txt").read_text() == "mine"


def test_overwrite_with_other_images_names_the_earlier_folders_it_leaves(
    tmp_path: Path, checkpoint: Path, inputs: Path, capsys
) -> None:
    out = tmp_path / "out"
    assert main([str(checkpoint), str(inputs), "--out", str(out), *FAST]) == 0  # cutout and photo
    (out / "mine").mkdir()  # a folder of the user's, not an image's: not named
    assert main([str(checkpoint), str(inputs / "photo.jpg"), "--out", str(out), "--overwrite", *FAST]) == 0
    assert (out / "cutout" / "mesh.glb").is_file()  # kept: nothing is deleted unasked
    record = json.loads((out / "reconstructions.json").read_text())
    assert [r["name"] for r in record["images"]] == ["photo"] and record["earlier_folders"] == ["cutout"]
    assert "Not shown: image folders of an earlier reconstruction" in (out / "index.html").read_text()
    assert 'href="cutout/"' in (out / "index.html").read_text()
    assert f"earlier reconstruction left in {out}: cutout\n" in capsys.readouterr().out
    # the same images again: nothing left over, nothing named
    assert main([str(checkpoint), str(inputs), "--out", str(out), "--overwrite", *FAST]) == 0
    assert "earlier_folders" not in json.loads((out / "reconstructions.json").read_text())
    assert "Not shown" not in (out / "index.html").read_text() and "earlier" not in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [(["--refine-parts", "bogus"], "--refine-parts: unknown refinement part(s) ['bogus']"),
     (["--refine-parts", "all"], "--refine-parts needs --refine STEPS")],
)  # fmt: skip
def test_refine_parts_without_refine_is_refused(tmp_path, checkpoint, inputs, capsys, extra, message) -> None:
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "out"), *FAST, *extra]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_strip_views_are_bounded(tmp_path: Path, checkpoint: Path, inputs: Path, capsys) -> None:
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "out"), *FAST, "--strip-views", "25"]) == 2
    assert "error: --strip-views must be at most 24" in capsys.readouterr().err


def test_an_out_below_a_file_is_refused_before_the_model_is_read(tmp_path, checkpoint, inputs, capsys, monkeypatch):
    import unicorn.io

    (tmp_path / "afile").write_text("mine")
    monkeypatch.setattr(unicorn.io, "load_model", lambda *a, **k: pytest.fail("the model was read"))
    assert main([str(checkpoint), str(inputs), "--out", str(tmp_path / "afile" / "sub"), *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"output folder {tmp_path / 'afile' / 'sub'}: {tmp_path / 'afile'} is a file" in err
    assert (tmp_path / "afile").read_text() == "mine"


@pytest.mark.parametrize(
    ("entry", "kind"),
    [("photo", "a file where a folder goes"), ("_viewer", "a file where a folder goes"),
     ("index.html", "a folder where a file goes"), ("photo", "a link where a folder goes")],
)  # fmt: skip
def test_an_entry_of_out_the_outputs_cannot_replace_is_refused_before_the_model_is_read(
    tmp_path, checkpoint, inputs, capsys, monkeypatch, entry, kind
):
    """With --overwrite, a file where an image's folder goes (or a folder where a file goes) is refused in one line
    before the model is read, not once every image is reconstructed; --out is left as it was."""
    import unicorn.io

    out = tmp_path / "out"
    out.mkdir()
    if kind.startswith("a folder"):
        (out / entry).mkdir()
        (out / entry / "mine.txt").write_text("mine")
    elif kind.startswith("a link"):
        (tmp_path / "elsewhere").mkdir()
        (out / entry).symlink_to(tmp_path / "elsewhere")
    else:
        (out / entry).write_text("mine")
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    monkeypatch.setattr(unicorn.io, "load_model", lambda *a, **k: pytest.fail("the model was read"))
    assert main([str(checkpoint), str(inputs), "--out", str(out), "--overwrite", *FAST]) == 2
    expected = f"cannot write the output folder {out}: {out / entry} is {kind}; move it away or choose another folder"
    assert capsys.readouterr().err == f"unicorn-reconstruct: error: {expected}\n"
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    assert {p.name for p in tmp_path.iterdir()} <= {"inputs", "out", "elsewhere"}  # no temporary folder left


def test_every_option_is_in_the_docs_options_table() -> None:
    from unicorn.cli.reconstruct import build_parser

    text = (Path(__file__).parents[2] / "docs" / "reconstruct.md").read_text(encoding="utf-8")
    table = text[text.index("## Options") : text.index("## What works best")]
    documented = {
        o
        for line in table.splitlines()
        if line.startswith("| `")
        for o in re.findall(r"`(--[\w-]+)", line.split("|")[1])
    }
    options = {o for action in build_parser()._actions for o in action.option_strings if o.startswith("--")}
    assert options - {"--help", "--version", "--debug"} <= documented  # --debug: docs/safety.md


def test_a_box_is_inclusive_in_the_upright_photo_and_padding_frames_cut_outs_too(tmp_path, checkpoint) -> None:
    """--bbox 5,30,24,49 with --padding 0 frames exactly those 20 x 20 pixels of the photo as viewers show it (stored
    sideways, EXIF orientation 6); --padding 0.5 grows a cut-out's opaque box by half its side on every side."""
    upright = _smooth_picture(60, 40)  # 40 wide, 60 tall as shown
    exif = Image.Exif()
    exif[0x0112] = 6  # shown turned by 90 degrees clockwise: stored 60 wide, 40 tall
    Image.fromarray(upright).transpose(Image.Transpose.ROTATE_90).save(tmp_path / "turned.png", exif=exif)
    cutout = np.zeros((60, 60, 4), dtype=np.uint8)
    cutout[10:30, 20:40] = 255  # opaque rows 10..29, columns 20..39
    Image.fromarray(cutout, "RGBA").save(tmp_path / "cutout.png")
    out = tmp_path / "out"
    fast = ["--turntable-frames", "0", "--strip-views", "1", "--view-size", "32", "--quiet", "--device", "cpu"]
    box = ["--bbox", "5,30,24,49", "--padding", "0"]
    assert main([str(checkpoint), str(tmp_path / "turned.png"), "--out", str(out / "box"), *box, *fast]) == 0
    frame = json.loads((out / "box" / "turned" / "pose.json").read_text())["frame"]
    assert frame == pytest.approx({"x": 5, "y": 30, "width": 20, "height": 20})
    seen = np.asarray(Image.open(out / "box" / "turned" / "input.png").convert("RGB"), dtype=np.float64)
    crop = upright[30:50, 5:25].astype(np.float64)
    assert np.abs(seen.mean((0, 1)) - crop.mean((0, 1))).max() < 3  # that crop's colours, in the upright photo
    stored = np.asarray(Image.open(tmp_path / "turned.png").convert("RGB"), dtype=np.float64)  # PIL: not turned
    assert np.abs(seen.mean((0, 1)) - stored[30:50, 5:25].mean((0, 1))).max() > 20  # not the stored grid's box
    padded = ["--padding", "0.5"]
    assert main([str(checkpoint), str(tmp_path / "cutout.png"), "--out", str(out / "cut"), *padded, *fast]) == 0
    frame = json.loads((out / "cut" / "cutout" / "pose.json").read_text())["frame"]
    assert frame == pytest.approx({"x": 20 - 10, "y": 10 - 10, "width": 40, "height": 40})


def _smooth_picture(height: int, width: int) -> np.ndarray:
    """(H, W, 3) uint8: red grows to the right, green downwards, a blue disc left of centre (a picture whose every
    shift or stretch shows)."""
    rows, cols = np.mgrid[0:height, 0:width] + 0.5
    disc = (cols - 0.3 * width) ** 2 + (rows - 0.6 * height) ** 2 < (0.25 * min(height, width)) ** 2
    return (np.stack([cols / width, rows / height, 0.8 * disc], axis=-1) * 255).round().astype(np.uint8)


@pytest.mark.parametrize(
    ("name", "extra"),
    [("photo.png", []), ("cutout.png", []), ("photo.png", ["--bbox", "40,-5,75,30"])],
    ids=["landscape-photo", "alpha-cutout", "box-beyond-the-edges"],
)
def test_mesh_projected_with_pose_json_lands_on_the_mask_placed_on_the_photo(
    tmp_path: Path, varied_checkpoint: Path, name: str, extra: list[str]
) -> None:
    """docs/reconstruct.md's recipe, computed here apart from the library: ``frame`` is the rectangle of the photo
    that input.png shows (the photo averaged over each of input.png's pixels there gives input.png), and
    mesh.obj's vertices through R, T and the focal length to NDC, then through ``frame`` to the photo, fill there
    (PIL polygons) the pixels that mask.png covers once placed on the photo through the same ``frame``."""
    from PIL import ImageDraw

    photos = {"photo.png": _smooth_picture(40, 70)}  # landscape, fitted and padded to a square
    cutout = np.zeros((60, 90, 4), dtype=np.uint8)  # object touching the top edge: its padded crop reaches beyond
    cutout[1:30, 50:89, :3], cutout[1:30, 50:89, 3] = _smooth_picture(29, 39), 255
    photos["cutout.png"] = np.where(cutout[..., 3:] > 0, cutout[..., :3], 255).astype(np.uint8)  # on white
    Image.fromarray(photos["photo.png"]).save(tmp_path / "photo.png")
    Image.fromarray(cutout, "RGBA").save(tmp_path / "cutout.png")
    out = tmp_path / "out"
    args = ["--view-size", "64", "--turntable-frames", "0", "--strip-views", "1", "--quiet", "--device", "cpu"]
    assert main([str(varied_checkpoint), str(tmp_path / name), "--out", str(out), *args, *extra]) == 0
    folder = out / Path(name).stem
    pose = json.loads((folder / "pose.json").read_text())
    x, y, width, height = (pose["frame"][k] for k in ("x", "y", "width", "height"))
    if extra or name == "cutout.png":  # the frame reaches beyond the photo's top
        assert y < 0

    # input.png: the photo's frame, each pixel the mean of 8 x 8 samples of the photo over it (its border beyond it)
    photo = photos[name].astype(np.float64) / 255
    seen = np.asarray(Image.open(folder / "input.png").convert("RGB"), dtype=np.float64) / 255
    side = seen.shape[0]
    offsets = (np.arange(8) + 0.5) / 8
    cols = x + (np.arange(side)[:, None] + offsets[None]).reshape(-1) / side * width
    rows = y + (np.arange(side)[:, None] + offsets[None]).reshape(-1) / side * height
    cols = np.clip(np.floor(cols).astype(int), 0, photo.shape[1] - 1)
    rows = np.clip(np.floor(rows).astype(int), 0, photo.shape[0] - 1)
    averaged = photo[rows][:, cols].reshape(side, 8, side, 8, 3).mean(axis=(1, 3))
    assert np.abs(averaged - seen).mean() < 0.006

    # mask.png against the mesh projected as the docs say
    lines = (folder / "mesh.obj").read_text().splitlines()
    verts = np.array([[float(v) for v in line.split()[1:4]] for line in lines if line.startswith("v ")])
    faces = [[int(c.split("/")[0]) - 1 for c in line.split()[1:]] for line in lines if line.startswith("f ")]
    view = verts @ np.array(pose["R"]) + np.array(pose["T"])
    ndc = pose["camera"]["focal_length_ndc"] * view[:, :2] / view[:, 2:]
    on_photo = np.stack([x + (1 - ndc[:, 0]) / 2 * width, y + (1 - ndc[:, 1]) / 2 * height], axis=1)
    # the same camera in OpenCV's convention (pixel centres at integers), on the photo and on input.png
    cv = {k: np.array(v) for k, v in pose["opencv"].items() if k != "convention"}
    cam = verts @ cv["R"].T + cv["t"]
    assert (cam[:, 2] > 0).all()
    for K, placed in ((cv["K"], on_photo), (cv["K_input"], (1 - ndc) / 2 * side)):
        np.testing.assert_allclose((cam @ K.T)[:, :2] / cam[:, 2:], placed - 0.5, atol=1e-4)
    # filled on a grid 4 times finer than mask.png over the frame, in photo pixels
    fine = 4 * 64
    canvas = Image.new("L", (fine, fine))
    draw = ImageDraw.Draw(canvas)
    scale = np.array([fine / width, fine / height])
    for face in faces:
        draw.polygon([tuple(((on_photo[k] - (x, y)) * scale).tolist()) for k in face], fill=255)
    filled = np.asarray(canvas) > 127
    shown = (np.asarray(Image.open(folder / "mask.png").convert("L")) > 127).repeat(4, 0).repeat(4, 1)
    assert shown.sum() > 16 * 100  # the object is in view
    assert (filled & shown).sum() / (filled | shown).sum() > 0.95
    # the two silhouettes' centres agree to a tenth of one of mask.png's pixels
    grid = np.stack(np.mgrid[0:fine, 0:fine], axis=-1)
    assert np.linalg.norm(grid[filled].mean(0) - grid[shown].mean(0)) / 4 < 0.1
