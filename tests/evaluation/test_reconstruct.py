"""Reconstruction helpers: output names and pose records (the command itself is tested in tests/cli)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch

from tests.support.evaluation import IMAGE_SIZE
from unicorn.evaluation.reconstruct import MAX_NAME, pose_record, reconstruct, unique_names
from unicorn.geometry.rotations import azim_elev_roll_to_rotation, look_at_view_parameters, look_at_view_transform
from unicorn.io.images import InputImage
from unicorn.io.staging import OutputConflictError


def test_unique_names() -> None:
    assert unique_names([Path("/x/a/0000.png"), Path("/x/b/0000.png"), Path("/x/b/1.jpg")]) == [
        "a_0000",
        "b_0000",
        "1",  # only the names that clash take their folders
    ]
    clash = [Path("/x/a/Photo.gif"), Path("/x/b/photo.tiff"), Path("/y/c/2.png"), Path("/x/a_photo.png")]
    assert unique_names(clash) == ["a_Photo", "b_photo", "2", "a_photo_1"]  # case-folded clash; a suffix settles
    assert unique_names([Path("/x/cat dog.png"), Path("/y/b.png")]) == ["cat_dog", "b"]
    assert unique_names([Path("/x/a.png"), Path("/x/a.jpg")]) == ["a", "a_1"]


def test_names_keep_every_script_in_one_unicode_form() -> None:
    paths = [Path("/x/車の写真.jpg"), Path("/x/cafe\u0301 #1.png"), Path("/x/Straße.png"), Path("/x/STRASSE.jpg")]
    assert unique_names(paths) == ["車の写真", "café_1", "Straße", "STRASSE_1"]  # NFC; ß and SS are one name folded
    assert unique_names([Path("/x/写真.png"), Path("/x/猫.png")]) == ["写真", "猫"]  # not "image" and "image_1"
    long = [Path("/x") / ("車" * 100 + k + ".jpg") for k in "12"]  # 300 bytes of UTF-8 each
    names = unique_names(long)
    assert len(set(names)) == 2 and all(len(n.encode()) <= MAX_NAME for n in names)
    assert all(n.startswith("車" * 30) for n in names)  # cut between characters


def test_long_names_are_cut_and_stay_unique() -> None:
    paths = [Path("/x") / ("a" * 200) / ("x" * 100 + ".jpg"), Path("/x") / ("b" * 200) / ("x" * 100 + ".jpg")]
    names = unique_names(paths)
    assert len(set(names)) == 2 and all(len(n.encode()) <= MAX_NAME for n in names)
    assert names[0].startswith("a" * 90) and names[1].startswith("b" * 90)
    same_start = [Path("/x") / ("a" * 150 + k) / "photo.png" for k in "12"]  # cut to the same first characters
    assert len(set(unique_names(same_start))) == 2


def test_pose_record(real_model) -> None:
    """pose.json's azimuth, elevation, distance, at and up are look_at_view_transform's: they give back R, T."""
    with torch.no_grad():
        pred = real_model.predict(torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE))
    record = json.loads(json.dumps(pose_record(real_model, pred, 1)))  # JSON-ready
    torch.testing.assert_close(torch.tensor(record["R"], dtype=torch.float64), pred.R[1].double())
    assert "look_at_view_transform" in record["convention"]
    R, T = look_at_view_transform(
        dist=torch.tensor(record["distance"], dtype=torch.float64),
        elev=record["elevation"],
        azim=record["azimuth"],
        at=torch.tensor(record["at"], dtype=torch.float64),
        up=torch.tensor(record["up"], dtype=torch.float64),
    )
    torch.testing.assert_close(R[0], pred.R[1].double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(T[0], pred.T[1].double(), atol=1e-6, rtol=0)
    assert abs(sum(record["candidate_probabilities"]) - 1) < 1e-5 and record["camera"]["fov_degrees"] > 0


def test_pose_record_of_a_centred_upright_camera(real_model) -> None:
    """A camera at azimuth a of the model's pose head (no roll, object centred) is look_at's azimuth a + 180."""
    with torch.no_grad():
        pred = real_model.predict(torch.rand(1, 3, IMAGE_SIZE, IMAGE_SIZE))
    pred.R[0] = azim_elev_roll_to_rotation(torch.tensor(30.0), torch.tensor(10.0), torch.tensor(0.0)).reshape(3, 3)
    pred.T[0] = torch.tensor([0.0, 0.0, 2.5])
    record = pose_record(real_model, pred, 0)
    assert abs(record["azimuth"] - (-150.0)) < 1e-4 and abs(record["elevation"] - 10.0) < 1e-4
    assert abs(record["distance"] - 2.5) < 1e-6 and abs(record["roll"]) < 1e-4
    assert torch.tensor(record["at"]).abs().max() < 1e-6
    # the defaults (at = origin, up = +Y) are enough for such a camera
    R, T = look_at_view_transform(record["distance"], record["elevation"], record["azimuth"])
    torch.testing.assert_close(R[0], pred.R[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(T[0], pred.T[0], atol=1e-5, rtol=0)


def test_look_at_view_parameters_round_trip() -> None:
    g = torch.Generator().manual_seed(0)
    angles = torch.rand(64, 3, generator=g) * torch.tensor([360.0, 170.0, 120.0]) - torch.tensor([180.0, 85, 60])
    R = azim_elev_roll_to_rotation(angles[:, 0], angles[:, 1], angles[:, 2]).double()
    T = (torch.randn(64, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0])).double()
    p = look_at_view_parameters(R, T)
    R2, T2 = look_at_view_transform(p["dist"], p["elev"], p["azim"], p["at"], p["up"])
    torch.testing.assert_close(R2, R, atol=1e-6, rtol=0)
    torch.testing.assert_close(T2, T, atol=1e-6, rtol=0)


def test_a_second_reconstruction_into_the_same_folder_changes_nothing_unless_asked(real_model, tmp_path) -> None:
    image = torch.rand(3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(0))
    items = [InputImage(tmp_path / "car.png", "car", image, cropped=False)]
    options = {"view_size": 32, "turntable_frames": 0, "strip_views": 1, "progress": False, "provenance": {}}
    reconstruct(real_model, items, tmp_path / "out", **options)
    before = {p: p.read_bytes() for p in sorted((tmp_path / "out").rglob("*")) if p.is_file()}
    other = [InputImage(tmp_path / "car.png", "car", 1 - image, cropped=False)]
    with pytest.raises(OutputConflictError, match=r"holds the outputs of an earlier reconstruction \(car, overview"):
        reconstruct(real_model, other, tmp_path / "out", **options)
    assert {p: p.read_bytes() for p in sorted((tmp_path / "out").rglob("*")) if p.is_file()} == before
    reconstruct(real_model, other, tmp_path / "out", overwrite=True, **options)
    assert (tmp_path / "out" / "car" / "input.png").read_bytes() != before[tmp_path / "out" / "car" / "input.png"]
    # another image into the same folder: the car's folder stays, named beside the new image's
    bike = [InputImage(tmp_path / "bike.png", "bike", image, cropped=False)]
    reconstruct(real_model, bike, tmp_path / "out", overwrite=True, **options)
    record = json.loads((tmp_path / "out" / "reconstructions.json").read_text())
    assert [r["name"] for r in record["images"]] == ["bike"] and record["earlier_folders"] == ["car"]
    assert (tmp_path / "out" / "car" / "pose.json").is_file()


def test_overwrite_removes_the_optional_files_of_an_earlier_call_that_it_does_not_write(real_model, tmp_path) -> None:
    """A folder written again holds one run's files: the earlier call's turntable GIF goes when this call writes
    none (as unicorn-reconstruct --overwrite removes it), the user's own files stay."""
    image = torch.rand(3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(0))
    items = [InputImage(tmp_path / "car.png", "car", image, cropped=False)]
    options = {"view_size": 32, "strip_views": 1, "progress": False, "provenance": {}}
    out = tmp_path / "out"
    reconstruct(real_model, items, out, turntable_frames=2, **options)
    assert (out / "car" / "turntable.gif").is_file()
    (out / "car" / "notes.txt").write_text("mine")
    records = reconstruct(real_model, items, out, turntable_frames=0, overwrite=True, **options)
    written = set(records[0]["files"].values())
    assert "turntable.gif" not in written
    assert {p.name for p in (out / "car").iterdir()} == written | {"notes.txt"}
    assert (out / "car" / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    ("names", "message"),
    [
        (["x", "X"], r"both named 'X' \(without regard to case\)"),
        (["index.html"], r"'index.html' .* is one of the output folder's own files"),
        (["../escape"], r"'../escape' .* is not a folder name"),
    ],
)
def test_names_that_cannot_each_be_a_folder_are_refused_before_anything_is_written(
    real_model, tmp_path, names, message
) -> None:
    """Two images of one name would share a folder (the second's meshes refused half-way, or with overwrite one
    folder for both); a reserved name is a file of the output folder; a path writes outside it."""
    image = torch.rand(3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(0))
    items = [InputImage(tmp_path / f"{i}.png", name, image, cropped=False) for i, name in enumerate(names)]
    options = {"view_size": 32, "turntable_frames": 0, "strip_views": 1, "progress": False, "provenance": {}}
    for overwrite in (False, True):
        with pytest.raises(ValueError, match=message):
            reconstruct(real_model, items, tmp_path / "sub" / "out", overwrite=overwrite, **options)
        assert not (tmp_path / "sub").exists()


@pytest.mark.parametrize("overwrite", [False, True])
def test_a_file_where_an_image_folder_goes_is_refused_before_anything_is_written(
    real_model, tmp_path, overwrite
) -> None:
    """The first image's folder is not written before the second's place turns out to be a file."""
    image = torch.rand(3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(0))
    items = [InputImage(tmp_path / f"{name}.png", name, image, cropped=False) for name in ("bike", "car")]
    out = tmp_path / "out"
    out.mkdir()
    (out / "car").write_text("mine")
    options = {"view_size": 32, "turntable_frames": 0, "strip_views": 1, "progress": False, "provenance": {}}
    message = f"cannot write the output folder {out}: {out / 'car'} is a file where a folder goes"
    with pytest.raises(OutputConflictError, match="^" + re.escape(message)):
        reconstruct(real_model, items, out, overwrite=overwrite, **options)
    assert [p.name for p in out.iterdir()] == ["car"] and (out / "car").read_text() == "mine"
