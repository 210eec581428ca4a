"""ShapeNet-NMR loader (DVR form) on the synthetic benchmark and on hand-written DVR cameras."""

from __future__ import annotations

import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml
from omegaconf import OmegaConf
from PIL import Image

from unicorn.data.images import DatasetError, DatasetNotFoundError, ImageLoadError
from unicorn.data.shapenet import (
    ShapeNetNMR,
    ViewCountError,
    ViewSizeError,
    dvr_to_unicorn_points,
    dvr_to_unicorn_pose,
    unicorn_to_dvr_points,
    unicorn_to_dvr_world_mat,
)
from unicorn.data.synthetic.sampling import views_to_cameras
from unicorn.geometry.cameras import PerspectiveCamera
from unicorn.geometry.rotations import look_at_view_transform

A_ROW = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
FLIP = np.diag([-1.0, -1.0, 1.0])


def test_pose_conversion_matches_reference_formula() -> None:
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R_dvr = q * np.sign(np.linalg.det(q))
    t = rng.normal(size=3)
    world_mat = np.eye(4)
    world_mat[:3, :3], world_mat[:3, 3] = R_dvr, t
    R, T = dvr_to_unicorn_pose(world_mat)
    assert np.allclose(R, A_ROW @ R_dvr.T @ FLIP)  # the reference's rotation
    assert np.allclose(T, t * [-1, -1, 1])  # translation flipped too (the reference copies it)
    assert np.allclose(unicorn_to_dvr_world_mat(R, T), world_mat)
    pts = rng.normal(size=(5, 3))
    assert np.allclose(dvr_to_unicorn_points(pts), pts @ A_ROW.T)
    assert np.allclose(unicorn_to_dvr_points(dvr_to_unicorn_points(pts)), pts)


def test_conversion_is_consistent_with_projection() -> None:
    """A DVR camera and its converted unicorn pose see the same point at mirrored OpenCV/NDC coordinates."""
    R, T = look_at_view_transform(2.732, 30.0, 45.0)
    R, T = R[0].double().numpy(), T[0].double().numpy() + [0.1, -0.05, 0.0]
    world_mat = unicorn_to_dvr_world_mat(R, T)
    p_uni = np.array([0.2, -0.1, 0.3])
    p_cv = world_mat[:3, :3] @ unicorn_to_dvr_points(p_uni) + world_mat[:3, 3]
    p_view = p_uni @ R + T
    assert np.allclose(p_view, p_cv * [-1, -1, 1])


def test_items_shapes_and_ranges(synth_nmr: Path) -> None:
    ds = ShapeNetNMR(synth_nmr, split="test", views="random", with_points=True)
    assert len(ds) == 2  # one test model per category, one view each
    ds = ShapeNetNMR(synth_nmr, categories=["chair", "car"], split="train", with_points=True, n_points=256)
    assert ds.n_views == 6 and len(ds) == 2 * 1 * 6  # 3 models: 1 train, 1 val, 1 test
    for i in (0, len(ds) - 1):
        item = ds[i]
        assert item["image"].shape == (3, 64, 64) and item["image"].dtype == torch.float32
        assert item["mask"].shape == (1, 64, 64) and set(item["mask"].unique().tolist()) <= {0.0, 1.0}
        assert 0 <= item["image"].min() and item["image"].max() <= 1
        assert item["R"].shape == (3, 3) and item["T"].shape == (3,) and item["has_pose"]
        assert item["points"].shape == (256, 3) and item["normals"].shape == (256, 3)
        assert abs(item["points"].abs().max().item() - 0.5) < 0.01  # ShapeNet normalisation
        assert torch.allclose(item["normals"].norm(dim=1), torch.ones(256), atol=2e-3)
        assert torch.allclose(item["R"] @ item["R"].T, torch.eye(3), atol=1e-5)
    # train items carry no points by default
    assert "points" not in ShapeNetNMR(synth_nmr, split="train")[0]


@pytest.mark.parametrize("fixture", ["synth_nmr", "synth_wild"])
def test_pose_round_trip(fixture: str, request: pytest.FixtureRequest) -> None:
    root = request.getfixturevalue(fixture)
    ds = ShapeNetNMR(root, split="train")
    for i in range(len(ds)):
        item = ds[i]
        with np.load(ds.model_dir(i) / "views.npz") as views:
            R, T = views_to_cameras({k: views[k].astype(np.float64) for k in views.files})
        v = int(item["view"])
        assert np.allclose(item["R"].numpy(), R[v], atol=1e-5)
        assert np.allclose(item["T"].numpy(), T[v], atol=1e-5)


@pytest.mark.parametrize("fixture", ["synth_nmr", "synth_wild"])
def test_projected_points_land_in_masks(fixture: str, request: pytest.FixtureRequest) -> None:
    root = request.getfixturevalue(fixture)
    ds = ShapeNetNMR(root, split="train", with_points=True)
    camera = PerspectiveCamera(fov=30.0)
    for i in range(0, len(ds), 3):
        item = ds[i]
        screen = camera.transform_points_screen(item["points"][None], item["R"][None], item["T"][None], 64)[0]
        col, row = screen[:, 0].round().long(), screen[:, 1].round().long()
        inside = (col >= 0) & (col < 64) & (row >= 0) & (row < 64)
        # masks are thresholded at half coverage, so sub-pixel parts may vanish: allow a 1-pixel margin
        dilated = F.max_pool2d(item["mask"][None], 3, 1, 1)[0, 0]
        hits = dilated[row[inside], col[inside]]
        assert hits.mean() == 1.0, f"item {i}: {1 - hits.mean():.3f} of the points project outside the mask"
        assert item["mask"][0][row[inside], col[inside]].mean() > 0.75


def test_random_views_are_seeded(synth_nmr: Path) -> None:
    a = ShapeNetNMR(synth_nmr, split="train", views="random", seed=3)
    b = ShapeNetNMR(synth_nmr, split="train", views="random", seed=3)
    assert len(a) == 2 and [int(a[i]["view"]) for i in range(2)] == [int(b[i]["view"]) for i in range(2)]


def test_include_test_adds_models(synth_nmr: Path) -> None:
    assert len(ShapeNetNMR(synth_nmr, "chair", split="train", include_test=True)) == 3 * 6


def test_categories_by_name_or_synset(synth_nmr: Path) -> None:
    assert ShapeNetNMR(synth_nmr, "synthetic_car").synsets == ["90000003"]
    assert ShapeNetNMR(synth_nmr, ["90000001"]).synsets == ["90000001"]
    with pytest.raises(ValueError, match="unknown ShapeNet category 'sofa'"):
        ShapeNetNMR(synth_nmr, "sofa")


def test_missing_root_and_files(tmp_path: Path, synth_nmr: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match=r"nowhere.*NMR_Dataset\.zip"):
        ShapeNetNMR(tmp_path / "nowhere")
    broken = tmp_path / "broken"
    shutil.copytree(synth_nmr, broken)
    (broken / "90000001" / "softras_val.lst").unlink()
    with pytest.raises(DatasetNotFoundError, match="softras_val.lst"):
        ShapeNetNMR(broken, "chair", split="val")
    (broken / "metadata.yaml").unlink()
    with pytest.raises(DatasetNotFoundError, match="metadata.yaml"):
        ShapeNetNMR(broken)


SYNSET = "03001627"


def _tiny_nmr(root: Path, size: int = 8) -> Path:
    """A DVR-layout dataset of one category, two models of three views of ``size`` pixels, in every split."""
    folder = root / SYNSET
    folder.mkdir(parents=True)
    (root / "metadata.yaml").write_text(yaml.safe_dump({SYNSET: {"id": SYNSET, "name": "chair"}}))
    for split in ("train", "val", "test"):
        (folder / f"softras_{split}.lst").write_text("m0\nm1\n")
    for model in ("m0", "m1"):
        (folder / model / "image").mkdir(parents=True)
        (folder / model / "mask").mkdir()
        for view in range(3):
            Image.new("RGB", (size, size), (128, 128, 128)).save(folder / model / "image" / f"{view:04d}.png")
            Image.new("L", (size, size), 255).save(folder / model / "mask" / f"{view:04d}.png")
        cameras = {"world_mat_0": np.eye(4), "world_mat_1": np.eye(4)[:3], "world_mat_2": np.eye(4)}  # (3, 4) too
        np.savez(folder / model / "cameras.npz", **cameras)
        points = np.linspace(-0.5, 0.5, 15).reshape(5, 3)  # reaching the unit cube's faces, as normalised clouds do
        np.savez(folder / model / "pointcloud.npz", points=points, normals=np.ones((5, 3)))
    return root


def test_tiny_dataset_reads(tmp_path: Path) -> None:
    ds = ShapeNetNMR(_tiny_nmr(tmp_path), split="test", with_points=True)
    assert len(ds) == 6 and ds.view_size == (8, 8)
    assert all(ds[i]["image"].shape == (3, 8, 8) and ds[i]["points"].shape == (5, 3) for i in range(6))


@pytest.mark.parametrize("n_points", [-5, 0, 2.5, True, "100"])
def test_a_point_count_that_is_not_a_whole_number_of_points_is_refused(tmp_path: Path, n_points: object) -> None:
    """``dataset.options.n_points``: refused when the dataset is made, not as an empty cloud or numpy's words at the
    first item."""
    with pytest.raises(DatasetError, match=f"n_points must be a whole number >= 1 .*, got {n_points!r}$"):
        ShapeNetNMR(_tiny_nmr(tmp_path), split="test", n_points=n_points)


def test_normals_change_frame_with_the_points(tmp_path: Path) -> None:
    """Points spanning 3-D and distinct normals: the item's points are the file's under one linear map L (found by
    least squares, the rotation A_ROW of the pose test), and its normals the file's under L's inverse transpose."""
    root = _tiny_nmr(tmp_path)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.45, 0.45, (6, 3))
    points[0, 0] = 0.5  # reaching the unit cube's faces
    normals = rng.normal(size=(6, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    for model in ("m0", "m1"):
        np.savez(root / SYNSET / model / "pointcloud.npz", points=points, normals=normals)
    item = ShapeNetNMR(root, split="test", with_points=True)[0]
    L, *_ = np.linalg.lstsq(points, item["points"].double().numpy(), rcond=None)
    assert np.allclose(points @ L, item["points"].double().numpy(), atol=1e-6)
    assert np.allclose(L, A_ROW.T, atol=1e-6)
    expected = normals @ np.linalg.inv(L).T
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    assert not np.allclose(expected, normals, atol=0.1)  # the frame change moves these normals
    assert np.allclose(item["normals"].double().numpy(), expected, atol=1e-6)


def test_only_the_views_own_files_count_as_views(tmp_path: Path) -> None:
    """macOS's resource forks (``._0000.png``) and other stray images beside the views are not views."""
    root = _tiny_nmr(tmp_path)
    images = root / SYNSET / "m0" / "image"
    for view in range(3):
        (images / f"._{view:04d}.png").write_bytes(b"\x00\x05\x16\x07 resource fork")
    Image.new("RGB", (8, 8)).save(images / "preview.png")
    ds = ShapeNetNMR(root, split="test")  # on_error="raise": none of them is read
    assert ds.n_views == 3 and len(ds) == 6 and all(ds[i]["image"].shape == (3, 8, 8) for i in range(6))


def test_unquoted_synsets_are_read_as_written(tmp_path: Path) -> None:
    """YAML 1.1 reads an unquoted 03001627 as the octal number 787351: the synsets are read as their text."""
    root = _tiny_nmr(tmp_path)
    (root / "metadata.yaml").write_text(f"{SYNSET}:\n  id: {SYNSET}\n  name: chair\n02691156:\n  id: 02691156\n")
    ds = ShapeNetNMR(root, categories=["chair"], split="test")
    assert ds.synsets == [SYNSET] and ds.metadata[SYNSET] == {"id": SYNSET, "name": "chair"}


def test_a_synset_read_as_a_number_is_refused_saying_to_quote_it(tmp_path: Path) -> None:
    """``categories: [03001627]`` in a config file reaches the loader as YAML 1.1's octal 787351."""
    root = _tiny_nmr(tmp_path)
    number = OmegaConf.create(f"categories: [{SYNSET}]").categories[0]
    assert number == int(SYNSET, 8)
    with pytest.raises(DatasetError, match=r"unknown ShapeNet category '787351'; a number: write synsets in quotes"):
        ShapeNetNMR(root, [number])
    with pytest.raises(DatasetError, match=r"unknown ShapeNet category 'sofa'; metadata.yaml lists"):
        ShapeNetNMR(root, ["sofa"])


def test_a_name_of_two_synsets_is_refused_naming_them(tmp_path: Path) -> None:
    """Synthetic chairs generated into a ShapeNet root (which keeps its categories) are also named ``chair``: the
    name picks neither silently; the synsets and the names only one of them has pick each."""
    from unicorn.data.synthetic.writer import generate_synthetic_dataset

    root = _tiny_nmr(tmp_path)
    tiny = {"n_models": 3, "n_views": 1, "image_size": 8, "supersample": 1, "n_points": 100, "progress": False}
    generate_synthetic_dataset(root, "chair", "nmr", **tiny)
    with pytest.raises(DatasetError, match="'chair' names several synsets") as info:
        ShapeNetNMR(root, "chair")
    assert "03001627 (chair)" in str(info.value) and "90000001 (chair,synthetic_chair)" in str(info.value)
    assert ShapeNetNMR(root, "synthetic_chair").synsets == ["90000001"]
    assert ShapeNetNMR(root, [SYNSET, "90000001"]).synsets == [SYNSET, "90000001"]


def test_unicorn_data_check_reads_categories_comma_or_space_separated(tmp_path: Path, capsys) -> None:
    """As ``unicorn-eval --categories`` and ``unicorn-data synth --category`` take them; ``--categories`` naming none
    is a usage error rather than a dataset without models."""
    from unicorn.cli import data as cli

    root = _tiny_nmr(tmp_path)
    shutil.copytree(root / SYNSET, root / "04256520")
    metadata = yaml.safe_load((root / "metadata.yaml").read_text())
    (root / "metadata.yaml").write_text(yaml.safe_dump({**metadata, "04256520": {"id": "04256520", "name": "sofa"}}))
    for categories in (["chair,sofa"], ["chair", "sofa"], ["chair,", "04256520"]):
        assert cli.main(["check", "shapenet_nmr", "--root", str(root), "--categories", *categories]) == 0
        assert capsys.readouterr().out.startswith("shapenet_nmr train: 12 items\n")  # 2 categories x 2 models x 3 views
    assert cli.main(["check", "shapenet_nmr", "--root", str(root), "--categories", "sofa"]) == 0
    assert capsys.readouterr().out.startswith("shapenet_nmr train: 6 items\n")
    assert cli.main(["check", "shapenet_nmr", "--root", str(root), "--categories"]) == 2
    err = capsys.readouterr().err
    assert err == "unicorn-data: error: --categories names no category; drop it to check every category\n"


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"- a\n- b\n", "expected a table .* got a list"),
        (b"", "expected a table .* got nothing"),
        (b"'03001627': chair\n", "synset '03001627' maps to a str"),
        (b"{'03001627': [unclosed\n", "as YAML: line 2, column 1: expected ',' or ']'"),
        (
            b"'03001627': !!python/object/apply:os.system ['touch PWNED']\n",
            "synset '03001627' maps to a list",
        ),  # the tag read as text
        (b"'03001627': {id: '03001627', name: 'caf\xe9'}\n", "line 1 of .*: not UTF-8 text"),
    ],
    ids=["list", "empty", "scalar-value", "syntax", "python-tag", "latin-1"],
)
def test_malformed_metadata_is_one_error_naming_it(
    tmp_path: Path, content: bytes, problem: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = _tiny_nmr(tmp_path / "nmr")
    (root / "metadata.yaml").write_bytes(content)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DatasetError, match=problem) as info:
        ShapeNetNMR(root)
    assert "metadata.yaml" in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "PWNED").exists()  # the python tag was refused, not run


def test_non_utf8_split_list_is_one_error_naming_it(tmp_path: Path) -> None:
    root = _tiny_nmr(tmp_path)
    (root / SYNSET / "softras_train.lst").write_bytes(b"m0\n\xff\xfem1\n")
    with pytest.raises(DatasetError, match=r"line 2 of .*softras_train\.lst: not UTF-8 text"):
        ShapeNetNMR(root)


def test_split_list_with_a_byte_order_mark_is_read(tmp_path: Path) -> None:
    root = _tiny_nmr(tmp_path)
    (root / SYNSET / "softras_train.lst").write_bytes(b"\xef\xbb\xbfm0\r\nm1\r\n")  # as Windows Notepad saves it
    assert len(ShapeNetNMR(root, split="train")) == len(ShapeNetNMR(root, split="val"))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-30])


def _save(**arrays: np.ndarray) -> Callable[[Path], None]:
    return lambda path: np.savez(path, **arrays)


@pytest.mark.parametrize(
    ("name", "damage", "problem"),
    [
        ("cameras.npz", lambda path: path.write_bytes(b"junk"), "not a numpy .npz archive"),
        ("cameras.npz", _truncate, "not a numpy .npz archive"),
        ("cameras.npz", _save(world_mat_0=np.array([{"a": 1}], dtype=object)), "Object arrays cannot be loaded"),
        ("cameras.npz", _save(world_mat_0=np.eye(4)), "no world_mat_1 for view 1"),
        ("cameras.npz", _save(world_mat_0=np.eye(3), world_mat_1=np.eye(3)), r"world_mat_0 must be .* got \(3, 3\)"),
        ("cameras.npz", _save(world_mat_0=np.full((4, 4), np.nan), world_mat_1=np.eye(4)), "must be a finite"),
        ("pointcloud.npz", lambda path: path.write_bytes(b"junk"), "not a numpy .npz archive"),
        ("pointcloud.npz", _save(pts=np.zeros((5, 3))), r"no 'points' array \(it holds \['pts'\]\)"),
        ("pointcloud.npz", _save(points=np.zeros((5, 3)), normals=np.zeros((5, 2))), r"normals must be a \(P, 3\)"),
        (
            "pointcloud.npz",
            _save(points=np.full((5, 3), 0.3), normals=np.ones((5, 3))),
            r"the points must reach the unit cube's faces \(max \|coord\| 0.5 \+- 0.01\), got 0.3000 over 5 points",
        ),
        ("pointcloud.npz", _save(points=np.full((5, 3), 5.0), normals=np.ones((5, 3))), r"got 5.0000 over 5 points"),
    ],
    ids=[
        "cam-junk",
        "cam-truncated",
        "cam-objects",
        "cam-no-view",
        "cam-3x3",
        "cam-nan",
        "pc-junk",
        "pc-no-points",
        "pc-normals",
        "pc-small",
        "pc-large",
    ],
)
def test_malformed_npz_is_one_error_naming_it(
    tmp_path: Path, name: str, damage: Callable[[Path], None], problem: str
) -> None:
    path = _tiny_nmr(tmp_path) / SYNSET / "m0" / name
    damage(path)
    ds = ShapeNetNMR(tmp_path, split="test", with_points=True, on_error="skip")
    with pytest.raises(DatasetError, match=problem) as info:
        for i in range(len(ds)):
            ds[i]
    assert str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("odd", ["mask", "image"])
def test_view_of_another_size_is_skipped_like_an_unreadable_image(tmp_path: Path, odd: str) -> None:
    root = _tiny_nmr(tmp_path)
    # the first view of the first model: the dataset's size is what most views have, not what the first has
    bad = root / SYNSET / "m0" / odd / "0000.png"
    Image.new("RGB" if odd == "image" else "L", (4, 4)).save(bad)
    ds = ShapeNetNMR(root)
    assert ds.view_size == (8, 8)
    with pytest.raises(ViewSizeError, match=rf"{odd}/0000\.png: 4 x 4 pixels \(H x W\), the dataset's views 8 x 8"):
        ds[0]
    assert issubclass(ViewSizeError, ImageLoadError)
    with pytest.warns(RuntimeWarning, match="0000.png"):
        item = ShapeNetNMR(root, on_error="skip")[0]
    assert int(item["index"]) == 1 and item["image"].shape == (3, 8, 8)


CAR = "02958343"


def _two_categories(root: Path, counts: dict[str, int] | None = None, n_views: int = 5) -> Path:
    """A DVR-layout dataset of chairs (7 models) and cars (5), ``n_views`` views of 4 pixels each, the same models in
    every split; every cloud is the same 12 points along x, so that a kept point's x tells which one it is."""
    counts = {SYNSET: 7, CAR: 5} if counts is None else counts
    names = {SYNSET: "chair", CAR: "car"}
    root.mkdir(parents=True, exist_ok=True)
    (root / "metadata.yaml").write_text(yaml.safe_dump({s: {"id": s, "name": names[s]} for s in counts}))
    points = np.zeros((12, 3))
    points[:, 0] = np.linspace(-0.5, 0.5, 12)
    for synset, n in counts.items():
        models = [f"m{i}" for i in range(n)]
        for split in ("train", "val", "test"):
            (root / synset).mkdir(parents=True, exist_ok=True)
            (root / synset / f"softras_{split}.lst").write_text("".join(f"{m}\n" for m in models))
        for model in models:
            folder = root / synset / model
            (folder / "image").mkdir(parents=True)
            (folder / "mask").mkdir()
            for view in range(n_views):
                Image.new("RGB", (4, 4), (40 * view, 0, 0)).save(folder / "image" / f"{view:04d}.png")
                Image.new("L", (4, 4), 255).save(folder / "mask" / f"{view:04d}.png")
            np.savez(folder / "cameras.npz", **{f"world_mat_{v}": np.eye(4) for v in range(n_views)})
            np.savez(folder / "pointcloud.npz", points=points, normals=np.ones((12, 3)))
    return root


def _views_and_subsets(ds: ShapeNetNMR) -> list[tuple[int, list[int]]]:
    """Each item's view and the cloud points it keeps (their indices along x; the file's x is the item's z)."""
    items = [ds[i] for i in range(len(ds))]
    return [(int(it["view"]), np.round((it["points"][:, 2].numpy() + 0.5) * 11).astype(int).tolist()) for it in items]


#: chair's and car's views and 3-point subsets of :func:`_two_categories`, as each category alone was drawn before
#: a category's draws depended on it alone (the results' single-category runs): seed -> [(view, subset)]
SINGLE_CATEGORY = {
    0: [
        (4, [7, 6, 8]),
        (3, [11, 5, 9]),
        (2, [3, 9, 0]),
        (1, [5, 9, 11]),
        (1, [5, 9, 4]),
        (0, [9, 6, 4]),
        (0, [6, 10, 4]),
    ],
    5: [
        (3, [8, 6, 0]),
        (4, [1, 9, 8]),
        (0, [8, 7, 2]),
        (4, [3, 7, 9]),
        (2, [3, 0, 7]),
        (2, [5, 7, 10]),
        (3, [8, 10, 0]),
    ],
}


@pytest.mark.parametrize("seed", [0, 5])
def test_a_single_category_draws_the_views_and_point_subsets_it_always_drew(tmp_path: Path, seed: int) -> None:
    root = _two_categories(tmp_path)
    for category, n in (("chair", 7), ("car", 5)):
        ds = ShapeNetNMR(root, category, split="test", views="random", with_points=True, n_points=3, seed=seed)
        assert _views_and_subsets(ds) == SINGLE_CATEGORY[seed][:n]


@pytest.mark.parametrize("seed", [0, 5])
def test_a_category_draws_the_same_views_and_subsets_beside_other_categories(tmp_path: Path, seed: int) -> None:
    """The evaluation's fixed view of each model and its kept points depend on that model alone: the cars of a
    chair-and-car dataset are seen and scored as the cars alone are, whatever the categories' order."""
    root = _two_categories(tmp_path)
    options = {"split": "test", "with_points": True, "n_points": 3, "seed": seed}
    chair = _views_and_subsets(ShapeNetNMR(root, "chair", views="random", **options))
    car = _views_and_subsets(ShapeNetNMR(root, "car", views="random", **options))
    assert _views_and_subsets(ShapeNetNMR(root, ["chair", "car"], views="random", **options)) == chair + car
    assert _views_and_subsets(ShapeNetNMR(root, ["car", "chair"], views="random", **options)) == car + chair
    # every view of every model: each model keeps its own points there too
    both = ShapeNetNMR(root, ["chair", "car"], views="all", **options)
    cars = ShapeNetNMR(root, "car", views="all", **options)
    assert [both.load_points(7 + k)[0].tolist() for k in range(5)] == [
        cars.load_points(k)[0].tolist() for k in range(5)
    ]


@pytest.mark.parametrize("views", ["all", "random"])
@pytest.mark.parametrize(("first", "other"), [(5, 3), (3, 5)], ids=["fewer", "more"])
def test_a_model_with_another_number_of_views_is_refused_naming_it(
    tmp_path: Path, views: str, first: int, other: int
) -> None:
    """Fewer views than the first model's: items of views it lacks; more: views left out, and the random view drawn
    from the first model's. Either is one error naming the model, or its items skipped like unreadable images."""
    root = _two_categories(tmp_path, {SYNSET: 2}, n_views=first)
    odd = root / SYNSET / "m1"
    shutil.rmtree(odd)
    _two_categories(tmp_path / "other", {SYNSET: 2}, n_views=other)
    shutil.copytree(tmp_path / "other" / SYNSET / "m1", odd)
    ds = ShapeNetNMR(root, split="test", views=views)
    assert ds.n_views == first
    m1 = [i for i in range(len(ds)) if ds.model_view(i)[0] == 1]
    for i in m1:
        message = f"wrong number of views in {odd}: {other} views, where every model needs the {first} of the first"
        with pytest.raises(ViewCountError, match=re.escape(message)) as info:
            ds[i]
        assert "\n" not in str(info.value)
    assert issubclass(ViewCountError, ImageLoadError)
    skipping = ShapeNetNMR(root, split="test", views=views, on_error="skip")
    with pytest.warns(RuntimeWarning, match="wrong number of views in .*m1"):
        items = [skipping[i] for i in range(len(ds))]
    assert all(int(item["model"]) == 0 for item in items)
