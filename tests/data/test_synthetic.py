"""The synthetic benchmark: shapes, renderer, determinism, cache and command line."""

from __future__ import annotations

import hashlib
import json
import socket
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from PIL import Image

from unicorn.cli import data as cli
from unicorn.data.images import DatasetError
from unicorn.data.synthetic import writer
from unicorn.data.synthetic.primitives import Texture
from unicorn.data.synthetic.render import BACKGROUND_KINDS, camera_rays, random_background, render_object
from unicorn.data.synthetic.sampling import sample_surface_points, sample_views, views_to_cameras
from unicorn.data.synthetic.shapes import CATEGORIES, Part, ProceduralObject, build_object
from unicorn.data.synthetic.writer import ensure_synthetic_dataset, generate_synthetic_dataset, synthetic_dataset_path
from unicorn.geometry.cameras import PerspectiveCamera

TINY = {"n_models": 3, "n_views": 2, "n_points": 200, "supersample": 2, "image_size": 32, "progress": False}


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_shapes_are_normalised_and_vary(category: str) -> None:
    a = build_object(category, np.random.default_rng(0))
    b = build_object(category, np.random.default_rng(1))
    for obj in (a, b):
        lo, hi = obj.mesh().bounds
        assert np.isclose((hi - lo).max(), 1.0) and np.allclose((hi + lo) / 2, 0.0, atol=1e-9)
    assert not np.allclose(a.mesh().bounds, b.mesh().bounds)  # per-instance proportions
    c = build_object(category, np.random.default_rng(0))
    assert np.array_equal(a.mesh().vertices, c.mesh().vertices)


def _turn_difference(obj: ProceduralObject, azimuths: np.ndarray, image_size: int = 32) -> np.ndarray:
    """Per azimuth a, how different the views from a and a + 180 (elevation 30) are; see the test below."""
    az = np.concatenate([azimuths, azimuths + 180.0])
    V = len(az)
    R, T = views_to_cameras(
        {
            "azim": az,
            "elev": np.full(V, 30.0),
            "roll": np.zeros(V),
            "dist": np.full(V, 2.732),
            "tx": np.zeros(V),
            "ty": np.zeros(V),
        }
    )
    images, cover = render_object(obj, R, T, image_size=image_size, supersample=3, key_light=np.array([0.0, 1.0, 0.0]))
    n = len(azimuths)
    union = (cover[:n] >= 0.5) | (cover[n:] >= 0.5)
    diff = np.abs(images[:n] - images[n:]).mean(axis=-1)
    return (diff * union).sum(axis=(1, 2)) / union.sum(axis=(1, 2))


def _symmetric_car() -> ProceduralObject:
    """Control: a car whose back is its front (body, centred cabin, four wheels placed symmetrically)."""
    solid = Texture("solid", np.array([[0.8, 0.2, 0.2], [0.8, 0.2, 0.2]]))
    dark = Texture("solid", np.array([[0.1, 0.1, 0.1], [0.1, 0.1, 0.1]]))
    body = trimesh.creation.box(extents=(1.0, 0.15, 0.45))
    cabin = trimesh.convex.convex_hull(
        [(sx * 0.25, 0.075, sz * 0.2) for sx in (-1, 1) for sz in (-1, 1)]
        + [(sx * 0.15, 0.2, sz * 0.17) for sx in (-1, 1) for sz in (-1, 1)]
    )
    wheels = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            wheel = trimesh.creation.cylinder(radius=0.08, height=0.06, sections=20)
            wheel.apply_translation((sx * 0.32, -0.08, sz * 0.2))
            wheels.append(wheel)
    parts = [
        Part("body", body, solid),
        Part("cabin", cabin, dark),
        Part("wheels", trimesh.util.concatenate(wheels), dark),
    ]
    return ProceduralObject("control", parts).normalise()


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_every_category_has_a_front(category: str) -> None:
    """A view and the same view turned by 180 degrees in azimuth are clearly different pictures.

    Measure: at 32 px (the benchmark's size) and elevation 30, the mean absolute RGB difference (in [0, 1],
    averaged over the channels) between the two images over the union of their foreground masks (coverage >=
    0.5; a pixel covered in one image only compares the object with the white background). The key light is
    vertical, so a turn about +Y changes nothing but the object's orientation: an object that looks the same
    from the back as from the front scores ~0 (the symmetric control below scores < 0.005). Every one of six
    azimuth pairs (0/180 ... 150/330) of each of six instances must score above 0.04.
    """
    control = _turn_difference(_symmetric_car(), np.arange(0.0, 180.0, 30.0))
    assert control.max() < 0.005
    for i in range(6):
        obj = build_object(category, np.random.default_rng([1, i]))
        score = _turn_difference(obj, np.arange(0.0, 180.0, 30.0))
        assert score.min() > 0.04, (category, i, score.round(3))


def test_surface_points_skip_buried_faces() -> None:
    # a post whose top half is buried inside a block: none of the samples may lie inside the block
    block = trimesh.creation.box(extents=(1.0, 0.5, 1.0))
    post = trimesh.creation.box(
        extents=(0.2, 1.0, 0.2), transform=trimesh.transformations.translation_matrix((0, -0.25, 0))
    )
    solid = Texture("solid", np.zeros((2, 3)))
    obj = ProceduralObject("test", [Part("block", block, solid), Part("post", post, solid)])
    points, normals = sample_surface_points(obj, 3000, np.random.default_rng(0))
    assert points.shape == (3000, 3) and np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    strictly_inside = np.all(np.abs(points) < np.array([0.5, 0.25, 0.5]) - 1e-6, axis=1)
    assert not strictly_inside.any()
    assert (points[:, 1] < -0.25 - 1e-6).sum() > 100  # the visible half of the post is sampled


def test_camera_rays_follow_the_pixel_convention() -> None:
    R, T = views_to_cameras(
        {
            "azim": np.array([30.0]),
            "elev": np.array([20.0]),
            "roll": np.array([10.0]),
            "dist": np.array([2.5]),
            "tx": np.array([0.1]),
            "ty": np.array([-0.05]),
        }
    )
    origins, dirs = camera_rays(R[0], T[0], 8, fov=30.0)
    # a point along the ray of pixel (row 2, col 5) projects back onto that pixel centre
    import torch

    point = origins[2 * 8 + 5] + 1.7 * dirs[2 * 8 + 5]
    screen = PerspectiveCamera(fov=30.0).transform_points_screen(
        torch.tensor(point)[None, None], torch.tensor(R), torch.tensor(T), 8
    )
    assert np.allclose(screen[0, 0, :2].numpy(), [5.0, 2.0], atol=1e-6)


def test_render_white_background_and_coverage() -> None:
    obj = build_object("car", np.random.default_rng(0))
    R, T = views_to_cameras(sample_views("nmr", 2, np.random.default_rng(0)))
    images, cover = render_object(obj, R, T, image_size=32, supersample=2)
    assert images.shape == (2, 32, 32, 3) and cover.shape == (2, 32, 32)
    assert np.allclose(images[:, 0, 0], 1.0) and cover[:, 0, 0].max() == 0  # corner: background
    assert (cover == 1).sum() > 20 and ((cover > 0) & (cover < 1)).any()  # anti-aliased edges


def test_generation_is_deterministic(tmp_path: Path) -> None:
    a = generate_synthetic_dataset(tmp_path / "a", "mug", "wild", seed=5, **TINY)
    b = generate_synthetic_dataset(tmp_path / "b", "mug", "wild", seed=5, **TINY)
    c = generate_synthetic_dataset(tmp_path / "c", "mug", "wild", seed=6, **TINY)
    da, db, dc = _digest(a), _digest(b), _digest(c)
    assert da == db
    assert len(da) == len(dc) and set(da.values()).isdisjoint(
        v for k, v in dc.items() if k.endswith(".png") or k.endswith(".npz")
    )
    meta = yaml.safe_load((a / "metadata.yaml").read_text())
    assert meta == {"90000006": {"id": "90000006", "name": "mug,synthetic_mug"}}
    lists = [(a / "90000006" / f"softras_{s}.lst").read_text().split() for s in ("train", "val", "test")]
    assert sorted(sum(lists, [])) == [f"mug_5_{i:05d}" for i in range(3)]


def outside(image: Path) -> np.ndarray:
    """The pixels (N, 3) of a generated view at least 2 px from its mask, in [0, 255]."""
    near = np.pad(np.asarray(Image.open(image.parent.parent / "mask" / image.name)) > 0, 2)
    near = np.stack([np.roll(near, (dy, dx), (0, 1)) for dy in range(-2, 3) for dx in range(-2, 3)]).any(0)
    return np.asarray(Image.open(image))[~near[2:-2, 2:-2]]


def test_backgrounds_follow_the_mode_unless_given(tmp_path: Path) -> None:
    options = {**TINY, "n_models": 3, "seed": 1}

    def outside_all(root: Path) -> np.ndarray:
        return np.concatenate([outside(image) for image in sorted(root.rglob("image/*.png"))])

    wild = generate_synthetic_dataset(tmp_path / "wild", "car", "wild", **options)
    white = generate_synthetic_dataset(tmp_path / "white", "car", "wild", backgrounds=False, **options)
    nmr_bg = generate_synthetic_dataset(tmp_path / "nmr", "car", "nmr", backgrounds=True, **options)
    assert (outside_all(wild) < 250).mean() > 0.5 and (outside_all(nmr_bg) < 250).mean() > 0.5
    assert (outside_all(white) >= 250).all()
    # the same views: the cameras depend on the mode only
    for cams in sorted(wild.rglob("cameras.npz")):
        other = np.load(white / cams.relative_to(wild))
        assert all(np.array_equal(v, other[k]) for k, v in np.load(cams).items())
    assert json.loads((white / "synthetic.json").read_text())["backgrounds"] is False


@pytest.mark.parametrize("kind", BACKGROUND_KINDS)
def test_random_background_draws_only_the_kinds_asked_for(kind: str) -> None:
    rng = np.random.default_rng(0)
    for _ in range(8):
        bg = random_background(rng, 24, (kind,))
        assert bg.shape == (24, 24, 3) and bg.min() >= 0.0 and bg.max() <= 1.0
        colours = np.unique(bg.reshape(-1, 3).round(6), axis=0)
        if kind == "solid":
            assert len(colours) == 1
        elif kind == "checker":
            assert len(colours) == 2
        elif kind == "gradient":  # many colours, all on the line through two of them
            singular = np.linalg.svd(colours - colours.mean(0), compute_uv=False)
            assert len(colours) > 2 and singular[1] < 1e-4 * singular[0]
        else:  # smooth noise: many colours, neighbouring pixels close
            assert len(colours) > 100
            assert np.abs(np.diff(bg, axis=0)).max() < 0.5 and np.abs(np.diff(bg, axis=1)).max() < 0.5


def test_background_kinds_are_checked_and_recorded(tmp_path: Path) -> None:
    options = {**TINY, "n_models": 3, "seed": 1}
    solid = generate_synthetic_dataset(tmp_path / "solid", "car", "wild", background_kinds=["solid"], **options)
    for image in sorted(solid.rglob("image/*.png")):
        behind = outside(image).astype(int)
        assert len(behind) and (np.abs(behind - behind[0]) <= 1).all()  # one colour behind the object
    assert json.loads((solid / "synthetic.json").read_text())["background_kinds"] == ["solid"]
    with pytest.raises(DatasetError, match="some of .*'stripes'"):
        generate_synthetic_dataset(tmp_path / "bad", "car", "wild", background_kinds=["stripes"], **options)
    with pytest.raises(DatasetError, match="but they are white"):
        generate_synthetic_dataset(tmp_path / "white", "car", "nmr", background_kinds=["noise"], **options)
    assert not (tmp_path / "bad").exists() and not (tmp_path / "white").exists()


@pytest.mark.parametrize("kinds", [("solid", "gradient"), ["solid", "gradient"], "solid"])
def test_a_cached_dataset_is_reused_whatever_the_options_type(tmp_path: Path, kinds: object) -> None:
    options = {k: v for k, v in TINY.items() if k not in ("n_models", "progress")}
    path = ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, background_kinds=kinds, **options)
    stamp = (path / "synthetic.json").stat().st_mtime_ns
    assert ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, background_kinds=kinds, **options) == path
    assert (path / "synthetic.json").stat().st_mtime_ns == stamp  # checked and reused, not generated again
    recorded = json.loads((path / "synthetic.json").read_text())
    expected = writer.generation_settings("car", "wild", 3, 0, background_kinds=kinds, **options)
    assert {k: recorded[k] for k in expected} == expected
    assert set(recorded) == set(expected)  # what generation_settings says is all of it
    reordered = ["gradient", "solid"] if kinds != "solid" else ["gradient"]  # another order draws other backgrounds
    with pytest.raises(writer.StaleSyntheticDataset, match="background_kinds"):
        ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, background_kinds=reordered, **options)


def test_the_modes_own_values_written_out_are_the_same_dataset(tmp_path: Path) -> None:
    options = {k: v for k, v in TINY.items() if k != "n_models"}
    path = ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, **options)  # every view option the mode's
    written_out = {"backgrounds": True, "background_kinds": list(BACKGROUND_KINDS), "roll": 15, "shift": 0.1}
    for key, value in written_out.items():
        assert ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, **options, **{key: value}) == path
    assert ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, **options, **written_out) == path
    assert writer.check_manifest(path, n_models=np.int64(3), image_size=np.int32(32))  # numpy scalars are numbers
    with pytest.raises(writer.StaleSyntheticDataset, match="roll=None \\(asked: 14\\)"):
        ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, **options, roll=14)
    with pytest.raises(writer.StaleSyntheticDataset, match="backgrounds=None \\(asked: False\\)"):
        ensure_synthetic_dataset(tmp_path, "car", "wild", 3, 0, **options, backgrounds=False)
    # a category joins a generated folder with the mode's values written out, and not with others
    small = {k: v for k, v in TINY.items() if k != "progress"}
    generate_synthetic_dataset(path, "mug", "wild", seed=0, **small, progress=False, backgrounds=True, roll=15.0)
    assert sorted(json.loads((path / "synthetic.json").read_text())["categories"]) == ["car", "mug"]
    with pytest.raises(writer.SyntheticOutputExistsError, match="shift=None \\(asked: 0.2\\)"):
        generate_synthetic_dataset(path, "lamp", "wild", seed=0, **small, progress=False, shift=0.2)


def test_generation_settings_names_an_option_it_does_not_record() -> None:
    with pytest.raises(TypeError, match="does not record: colour"):
        writer.generation_settings("car", "wild", 3, 0, colour="red")


def test_wild_roll_and_shift_change_only_their_draws() -> None:
    default = sample_views("wild", 64, np.random.default_rng(3))
    flat = sample_views("wild", 64, np.random.default_rng(3), roll=0, shift=0)
    narrow = sample_views("wild", 64, np.random.default_rng(3), roll=5.0, shift=0.05)
    for key in ("azim", "elev", "dist"):
        assert np.array_equal(default[key], flat[key]) and np.array_equal(default[key], narrow[key])
    assert not flat["roll"].any() and not flat["tx"].any() and not flat["ty"].any()
    assert np.abs(default["roll"]).max() > 10  # the default's +-15 degrees
    # a uniform draw scaled: the same views, turned and shifted a third and a half as far
    assert np.allclose(narrow["roll"], default["roll"] / 3) and np.allclose(narrow["tx"], default["tx"] / 2)


def _project(cameras: np.lib.npyio.NpzFile, view: int, point: list[float]) -> np.ndarray:
    """A DVR-frame point projected through a view's stored camera, (2,) in normalised image units."""
    q = cameras[f"camera_mat_{view}"] @ cameras[f"world_mat_{view}"] @ np.array([*point, 1.0])
    return q[:2] / q[2]


def test_upright_centred_wild_views(tmp_path: Path) -> None:
    options = {**TINY, "n_views": 4}
    flat = generate_synthetic_dataset(tmp_path / "flat", "car", "wild", roll=0, shift=0, **options)
    default = generate_synthetic_dataset(tmp_path / "default", "car", "wild", **options)
    for path in sorted(flat.rglob("cameras.npz")):
        cams, other = np.load(path), np.load(default / path.relative_to(flat))
        for view in range(4):
            # the object's centre in the middle of the image, its vertical axis (DVR y) drawn vertical
            assert np.allclose(_project(cams, view, [0, 0, 0]), 0, atol=1e-6)
            assert abs(_project(cams, view, [0, 0.3, 0])[0]) < 1e-6
            assert not np.allclose(_project(other, view, [0, 0, 0]), 0, atol=1e-3)
    assert json.loads((flat / "synthetic.json").read_text())["roll"] == 0
    with pytest.raises(DatasetError, match="roll=5 is for the wild mode"):
        generate_synthetic_dataset(tmp_path / "nmr", "car", "nmr", roll=5, **options)
    with pytest.raises(DatasetError, match="shift must be a number in \\[0, 1\\], got -0.1"):
        generate_synthetic_dataset(tmp_path / "neg", "car", "wild", shift=-0.1, **options)
    assert not (tmp_path / "nmr").exists() and not (tmp_path / "neg").exists()
    # a dataset is not reused for other ranges
    ensure_synthetic_dataset(tmp_path / "cache", "car", "wild", **options, roll=0)
    with pytest.raises(writer.StaleSyntheticDataset, match="roll=0 \\(asked: None\\)"):
        ensure_synthetic_dataset(tmp_path / "cache", "car", "wild", **options)


def test_ensure_uses_cache_once_and_atomically(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    options = {k: v for k, v in TINY.items() if k != "n_models"}

    def interrupted(out: Path, *args: object, **kwargs: object) -> None:
        Path(out).mkdir(parents=True)
        (Path(out) / "partial").write_text("")
        raise KeyboardInterrupt

    monkeypatch.setattr(writer, "generate_synthetic_dataset", interrupted)
    with pytest.raises(KeyboardInterrupt):
        ensure_synthetic_dataset(None, "lamp", "nmr", 3, 0, **options)
    expected = synthetic_dataset_path("lamp", "nmr", 3, 0)
    assert expected.parent == tmp_path / "cache" / "synthetic"
    assert not expected.exists() and list(expected.parent.iterdir()) == []  # nothing half-written left

    monkeypatch.undo()
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    path = ensure_synthetic_dataset(None, "lamp", "nmr", 3, 0, **options)
    assert path == expected and (path / "synthetic.json").exists()
    stamp = (path / "synthetic.json").stat().st_mtime_ns
    monkeypatch.setattr(writer, "generate_synthetic_dataset", interrupted)  # would fail if called again
    assert ensure_synthetic_dataset(None, "lamp", "nmr", 3, 0, **options) == path
    assert (path / "synthetic.json").stat().st_mtime_ns == stamp
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_a_category_joins_a_generated_folder_only_once_and_with_its_settings(tmp_path: Path) -> None:
    out = generate_synthetic_dataset(tmp_path / "data", "mug", "nmr", seed=3, **TINY)
    before = _digest(out)
    for seed in (3, 4):  # the same models, or other ones whose lists would replace these
        with pytest.raises(writer.SyntheticOutputExistsError, match=r"already holds mug models"):
            generate_synthetic_dataset(out, ["lamp", "mug"], "nmr", seed=seed, **TINY)
    assert _digest(out) == before
    with pytest.raises(writer.SyntheticOutputExistsError, match=r"generated with seed=3 \(asked: 4\)"):
        generate_synthetic_dataset(out, "lamp", "nmr", seed=4, **TINY)  # synthetic.json could not describe both
    assert _digest(out) == before
    generate_synthetic_dataset(out, "lamp", "nmr", seed=3, **TINY)  # another category, the same settings, joins
    assert sorted(yaml.safe_load((out / "metadata.yaml").read_text())) == sorted(
        CATEGORIES[c][0] for c in ("lamp", "mug")
    )
    writer.check_manifest(out, categories=["lamp", "mug"], mode="nmr", n_models=3, seed=3)  # describes both


@pytest.mark.parametrize(
    "table",
    [
        "# DVR's NMR_Dataset form: unquoted synsets\n03001627:\n  id: 03001627\n  name: chair\n",
        "{03001627: {id: 03001627, name: chair}}",  # flow style, no final newline: written anew
    ],
)
def test_generating_into_a_shapenet_root_keeps_its_categories(tmp_path: Path, table: str) -> None:
    from unicorn.data.shapenet import read_metadata

    root = tmp_path / "nmr"
    root.mkdir()
    (root / "metadata.yaml").write_text(table)
    generate_synthetic_dataset(root, "mug", "nmr", seed=0, **TINY)
    text = (root / "metadata.yaml").read_text()
    if table.endswith("\n"):  # the user's bytes kept, the new category appended
        assert text.startswith(table)
    mug = CATEGORIES["mug"][0]
    assert read_metadata(root) == {
        "03001627": {"id": "03001627", "name": "chair"},  # not YAML 1.1 octal 787351
        mug: {"id": mug, "name": "mug,synthetic_mug"},
    }
    assert [p.name for p in root.iterdir() if p.name.startswith(".")] == []


def test_a_metadata_write_that_fails_leaves_the_users_file_and_no_temporary_one(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text("03001627:\n  id: 03001627\n  name: chair\n")
    real_write = Path.write_text

    def full_disk(self: Path, *args: object, **kwargs: object) -> int:
        real_write(self, "03001627:\n  id: 0300")  # part of it written, then the disk is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full_disk)
    with pytest.raises(OSError, match="No space left"):
        writer._write_metadata(path, {"03001627": {"id": "03001627", "name": "chair"}, "x": {"id": "x", "name": "x"}})
    monkeypatch.undo()
    assert path.read_text() == "03001627:\n  id: 03001627\n  name: chair\n"
    assert [p.name for p in tmp_path.iterdir()] == ["metadata.yaml"]


def test_cli_synth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli"
    code = cli.main(
        [
            "synth",
            "--category",
            "chair,table",
            "--mode",
            "nmr",
            "--models",
            "3",
            "--out",
            str(out),
            "--seed",
            "0",
            "--views",
            "2",
            "--size",
            "32",
            "--points",
            "100",
            "--supersample",
            "1",
            "--quiet",
        ]
    )
    assert code == 0 and "wrote 3 models x 2 categories" in capsys.readouterr().out
    assert (out / "90000001").is_dir() and (out / "90000002").is_dir()
    assert len(list((out / "90000002").glob("*/image/0001.png"))) == 3
    assert cli.main(["check", "synthetic", "--root", str(out), "--categories", "table"]) == 0
    assert "image: (3, 32, 32) torch.float32" in capsys.readouterr().out


def test_cli_synth_into_the_cache_says_whether_it_generated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    small = ["--category", "mug", "--models", "3", "--views", "2", "--size", "32", "--points", "100", "--quiet"]
    assert cli.main(["synth", *small]) == 0
    assert "wrote 3 models x 1 category to" in capsys.readouterr().out
    path = synthetic_dataset_path("mug", "nmr", 3, 0)
    stamp = (path / "synthetic.json").stat().st_mtime_ns
    assert cli.main(["synth", *small]) == 0  # found in the cache: nothing generated, and it says so
    out = capsys.readouterr().out
    assert out.strip() == f"{path} already holds 3 models x 1 category with these settings"
    assert (path / "synthetic.json").stat().st_mtime_ns == stamp


def test_cli_synth_view_ranges(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    small = ["--category", "car", "--models", "3", "--views", "2", "--size", "32", "--points", "100", "--quiet"]
    out = tmp_path / "flat"
    assert cli.main(["synth", "--mode", "wild", "--roll", "0", "--shift", "0", "--out", str(out), *small]) == 0
    settings = json.loads((out / "synthetic.json").read_text())
    assert (settings["roll"], settings["shift"]) == (0, 0)
    assert all(not np.load(p)["roll"].any() for p in out.rglob("views.npz"))
    capsys.readouterr()
    assert cli.main(["synth", "--mode", "nmr", "--roll", "5", "--out", str(tmp_path / "nmr"), *small]) != 0
    assert capsys.readouterr().err.startswith("unicorn-data: error: --roll=5.0 is for the wild mode;")


def test_cache_is_versioned_and_checked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    options = {k: v for k, v in TINY.items() if k != "n_models"}
    path = ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, **options)
    assert path.name.endswith(f"_v{writer.GENERATOR_VERSION}")
    assert writer.check_manifest(path, image_size=32)["generator_version"] == writer.GENERATOR_VERSION
    # the same folder asked for with another image size: an error that names it, not a silent reuse
    with pytest.raises(writer.StaleSyntheticDataset, match="image_size=32 \\(asked: 64\\)") as info:
        ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, **{**options, "image_size": 64})
    # the folder's name holds no image size: the message says how a training run generates it elsewhere
    assert str(info.value).endswith(
        "; delete that folder to generate it again, or generate it under another root (dataset.root=DIR in a "
        "training run)"
    )
    # an option left out means the generator's default (64 px), which this dataset was not made with
    with pytest.raises(writer.StaleSyntheticDataset, match="image_size"):
        ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, n_views=2, n_points=200, supersample=2, progress=False)
    # so does one asked for with backgrounds it was not made with: named alone, not the kinds that follow from it
    with pytest.raises(writer.StaleSyntheticDataset, match="backgrounds=None \\(asked: True\\);") as info:
        ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, **options, backgrounds=True)
    assert "background_kinds" not in str(info.value)
    with pytest.raises(writer.StaleSyntheticDataset) as info:
        ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, **options, backgrounds=True, background_kinds="noise")
    assert "with backgrounds=None (asked: True), background_kinds=None (asked: ['noise']);" in str(info.value)
    # a dataset written by another generator version is refused even under the current folder name
    settings = json.loads((path / "synthetic.json").read_text())
    settings["generator_version"] = writer.GENERATOR_VERSION - 1
    (path / "synthetic.json").write_text(json.dumps(settings))
    with pytest.raises(writer.StaleSyntheticDataset, match="generator_version"):
        ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, **options)
    # a damaged record (cut short, or JSON of another kind) is one error naming it
    for damaged in (json.dumps(settings)[:40], "[1, 2]", "\udcff"):
        (path / "synthetic.json").write_text(damaged, errors="surrogateescape")
        with pytest.raises(writer.StaleSyntheticDataset, match=r"synthetic\.json is damaged .*delete") as info:
            ensure_synthetic_dataset(tmp_path, "mug", "nmr", 3, 0, **options)
        assert "\n" not in str(info.value)
    # and a newer generator version names a new folder, so the old one is never picked up
    monkeypatch.setattr(writer, "GENERATOR_VERSION", writer.GENERATOR_VERSION + 1)
    assert synthetic_dataset_path("mug", "nmr", 3, 0, tmp_path) != path


def test_a_killed_generations_folder_is_removed_by_the_next(tmp_path: Path) -> None:
    """A SIGKILL while generating leaves its temporary folder: the next generation of that dataset removes it, and
    leaves alone those of live processes and of other machines (a cache shared over the network)."""
    import os
    import socket
    import subprocess
    import sys

    options = {k: v for k, v in TINY.items() if k not in ("n_models", "progress")}
    final = synthetic_dataset_path("car", "nmr", 3, 0, tmp_path)
    final.parent.mkdir(parents=True, exist_ok=True)
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    host = socket.gethostname()
    dead = final.parent / f".{final.name}.tmp-{host}-{gone.stdout.strip()}-0123abcd"
    live = final.parent / f".{final.name}.tmp-{host}-{os.getpid()}-4567cdef"
    remote = final.parent / f".{final.name}.tmp-another-host-{gone.stdout.strip()}-89abcdef"
    for folder in (dead, live, remote):
        (folder / "image").mkdir(parents=True)
    assert ensure_synthetic_dataset(tmp_path, "car", "nmr", 3, 0, **options) == final
    assert not dead.exists() and live.is_dir() and remote.is_dir()


def test_a_second_generation_of_a_dataset_waits_for_the_first_and_reuses_it(tmp_path: Path) -> None:
    import threading

    options = {k: v for k, v in TINY.items() if k not in ("n_models", "progress")}
    final = synthetic_dataset_path("car", "nmr", 3, 0, tmp_path)
    found = []
    with writer.generation_lock(final):  # another process generating this dataset holds it
        waiting = threading.Thread(
            target=lambda: found.append(ensure_synthetic_dataset(tmp_path, "car", "nmr", 3, 0, **options))
        )
        waiting.start()
        waiting.join(1.0)
        assert waiting.is_alive() and not list(tmp_path.glob(f".{final.name}.tmp-*"))  # waits, generates nothing
        stale = tmp_path / f".{final.name}.tmp-{socket.gethostname()}-{2**22 + 7}-0123abcd"  # a pid of no process
        (stale / "image").mkdir(parents=True)  # left alone while the other process runs: it may be its own
        generate_synthetic_dataset(final, "car", "nmr", 3, 0, **options)  # what the other process moves in
        stamp = (final / "synthetic.json").stat().st_mtime_ns
    waiting.join(120)
    assert found == [final] and (final / "synthetic.json").stat().st_mtime_ns == stamp  # reused, not made again
    assert stale.is_dir() and sorted(p.name for p in tmp_path.iterdir()) == sorted([final.name, stale.name])


def test_a_root_under_a_file_is_refused_naming_the_file(tmp_path: Path) -> None:
    """``dataset.root`` naming a file (or a folder under one): one line naming the file, which is left as it was."""
    options = {k: v for k, v in TINY.items() if k not in ("n_models", "progress")}
    (tmp_path / "notes").write_text("mine")
    for root in (tmp_path / "notes", tmp_path / "notes" / "data"):
        final = synthetic_dataset_path("car", "nmr", 3, 0, root)
        with pytest.raises(NotADirectoryError) as info:
            ensure_synthetic_dataset(root, "car", "nmr", 3, 0, **options)
        assert str(info.value) == f"cannot write {final}: {tmp_path / 'notes'} is a file, where a folder goes"
    assert [p.name for p in tmp_path.iterdir()] == ["notes"] and (tmp_path / "notes").read_text() == "mine"


def test_a_folder_that_is_not_a_generated_dataset_is_refused_before_generating(tmp_path: Path) -> None:
    options = {k: v for k, v in TINY.items() if k not in ("n_models", "progress")}
    final = synthetic_dataset_path("car", "nmr", 3, 0, tmp_path)
    final.mkdir(parents=True)
    (final / "notes.txt").write_text("mine")
    with pytest.raises(writer.StaleSyntheticDataset, match=r"holds files but no synthetic\.json") as info:
        ensure_synthetic_dataset(tmp_path, "car", "nmr", 3, 0, **options)
    assert "\n" not in str(info.value) and sorted(p.name for p in tmp_path.iterdir()) == [final.name]
    assert [p.name for p in final.iterdir()] == ["notes.txt"]


def test_two_synths_into_one_folder_both_land(tmp_path: Path, capsys) -> None:
    import threading
    import time

    out = tmp_path / "data"
    small = ["--models", "10", "--views", "1", "--size", "8", "--points", "100", "--quiet"]
    codes = []

    def synth(category: str) -> None:
        codes.append(cli.main(["synth", "--out", str(out), "--category", category, *small]))

    runs = [threading.Thread(target=synth, args=(category,)) for category in ("car", "chair")]
    runs[0].start()
    time.sleep(0.3)  # the second starts while the first generates: it waits, then joins its category to the first's
    runs[1].start()
    for run in runs:
        run.join(120)
    assert codes == [0, 0]
    assert yaml.safe_load((out / "metadata.yaml").read_text()).keys() == {"90000001", "90000003"}
    assert sorted(json.loads((out / "synthetic.json").read_text())["categories"]) == ["car", "chair"]
    assert not list(tmp_path.glob(".*"))  # no lock file or staging folder left


def test_a_category_named_twice_is_refused_before_anything_is_generated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    small = ["--models", "3", "--views", "2", "--size", "16", "--points", "100", "--supersample", "1", "--quiet"]
    message = "synthetic category 'car' is named twice in ['car', 'car']; name each category once"
    for where in (["--out", str(tmp_path / "synC")], []):  # a folder of the user's, and the cache
        for category in (["--category", "car,car"], ["--category", "car", "--category", "car"]):
            assert cli.main(["synth", *category, *where, *small]) == 2
            assert capsys.readouterr().err == f"unicorn-data: error: {message}\n"
    assert list(tmp_path.iterdir()) == []  # nothing written: no folder, no staging sibling, no lock
    with pytest.raises(DatasetError, match=r"^synthetic category 'car' is named twice"):
        ensure_synthetic_dataset(tmp_path, ["car", "chair", "car"], "nmr", 3, 0, progress=False)
    with pytest.raises(DatasetError, match=r"^synthetic category 'car' is named twice"):
        writer.check_synthetic_settings(["car", "car"], {"n_models": 3})  # a training config's
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("category", sorted(CATEGORIES))
def test_a_few_surface_points_reach_the_unit_cube_faces(category: str) -> None:
    """A few points may all miss an object's farthest part (a wing tip): the cloud still reaches within the
    evaluation's tolerance of 0.5, stored as float16 too, every point on the surface with a unit normal."""
    from unicorn.metrics.mesh_evaluator import GT_EXTENT_TOLERANCE

    for i in range(4):
        obj = build_object(category, np.random.default_rng([2, i]))
        points, normals = sample_surface_points(obj, 20, np.random.default_rng([3, i]))
        assert abs(np.abs(points.astype(np.float16)).max() - 0.5) <= GT_EXTENT_TOLERANCE / 2, (category, i)
        triangles = obj.mesh().triangles
        for point in points:  # on the surface: on one of the triangles
            nearest = trimesh.triangles.closest_point(triangles, np.broadcast_to(point, (len(triangles), 3)))
            assert np.linalg.norm(nearest - point, axis=1).min() < 1e-9
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_cli_synth_with_few_points_writes_clouds_the_evaluation_reads(tmp_path: Path) -> None:
    """``--points 20``: every model's cloud reaches the unit cube's faces, which the loader checks of a ground
    truth (as the evaluation does)."""
    from unicorn.data.shapenet import ShapeNetNMR

    out = tmp_path / "few"
    small = ["--models", "3", "--views", "1", "--size", "8", "--supersample", "1", "--quiet"]
    assert cli.main(["synth", "--category", "airplane,mug", "--points", "20", "--out", str(out), *small]) == 0
    ds = ShapeNetNMR(out, split="train", include_test=True, with_points=True)
    assert len(ds.models) == 6
    for model in range(len(ds.models)):
        points, _ = ds.load_points(model)
        assert points.shape == (20, 3)
