"""CUB-200-2011 (CMR annotations) and Pascal3D+ Car (UCMR annotations) loaders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch
from PIL import Image

from tests.support.checkpoints import deflated_torch_file
from tests.support.datasets import make_record, save_with_orientation, write_struct_array
from unicorn.data.cub import CUB200, CUB_KEYPOINTS
from unicorn.data.images import DatasetError, DatasetNotFoundError, ImageLoadError
from unicorn.data.matlab import load_struct_array
from unicorn.data.p3d import Pascal3DCar


def _check_item(
    item: dict, img_size: int, mask_size: int, n_kp: int, hand: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
) -> None:
    """An item's shapes, ranges and dummy pose, keypoints on the mask; with ``hand`` (see :func:`_hand_item`), its
    image, mask and keypoints against that hand computation from the annotation."""
    assert item["image"].shape == (3, img_size, img_size) and item["image"].dtype == torch.float32
    assert 0 <= item["image"].min() and item["image"].max() <= 1
    assert item["mask"].shape == (1, mask_size, mask_size) and set(item["mask"].unique().tolist()) <= {
        0.0,
        1.0,
    }
    assert item["mask"].sum() > 0
    assert item["R"].shape == (3, 3) and item["T"].shape == (3,) and not item["has_pose"]
    assert torch.equal(item["R"], torch.eye(3)) and torch.allclose(item["T"], torch.tensor([0.0, 0.0, 2.732]))
    kps = item["keypoints"]
    assert kps.shape == (n_kp, 3) and kps.dtype == torch.float32
    vis = kps[:, 2] > 0
    # the fixture's keypoints lie inside the objects, so they land on the mask
    col, row = kps[vis, 0].round().long(), kps[vis, 1].round().long()
    assert ((col >= 0) & (col < mask_size) & (row >= 0) & (row < mask_size)).all()
    assert item["mask"][0, row, col].min() == 1.0
    if hand is not None:
        image, mask, keypoints = hand
        # the hand crop is resized in 8 bits, as the reference's PIL images are; the loader resizes floats
        assert np.abs(item["image"].permute(1, 2, 0).numpy() - image).max() <= 1.0 / 255
        assert np.array_equal(item["mask"][0].numpy(), mask)
        assert np.allclose(kps.numpy(), keypoints, atol=1e-4)


# --------------------------------------------------------------------- items against a hand crop of a coded image
CODED_W, CODED_H = 50, 40
#: (x1, y1, x2, y2), 1-based and inclusive as in the .mat files: a box inside the image, and one at its top-left
#: corner whose square crop leaves the image
CODED_BOXES = ((11, 9, 30, 24), (1, 1, 20, 28))
#: left/right keypoints, 0-based, written out by hand: CUB's LEye/REye, LLeg/RLeg, LWing/RWing (its order: back,
#: beak, belly, breast, crown, forehead, left eye, left leg, left wing, nape, right eye, right leg, right wing, tail,
#: throat) and the pairs of the car_kps.mat written below (1-based 1<->2, 3<->4, ...)
CUB_PAIRS = {6: 10, 7: 11, 8: 12}
P3D_PAIRS = {0: 1, 2: 3, 4: 5, 6: 7, 8: 9, 10: 11}
INVISIBLE_KP = 5  # CUB's forehead; the car's 6th, paired with the 5th


def _coded_image() -> np.ndarray:
    """(H, W, 3) uint8 whose colour says where a pixel is: red 10 + 4 x, green 10 + 4 y (0-based), blue 128."""
    yy, xx = np.mgrid[0:CODED_H, 0:CODED_W]
    return np.stack([10 + 4 * xx, 10 + 4 * yy, np.full_like(xx, 128)], axis=-1).astype(np.uint8)


def _coded_parts(box: tuple[int, int, int, int], n_kp: int) -> np.ndarray:
    """(3, K) keypoints (x, y, visible), 1-based, on a grid of distinct pixels inside ``box``; one invisible."""
    k = np.arange(n_kp)
    parts = np.stack([box[0] + 3 + 3 * (k % 5), box[1] + 3 + 6 * (k // 5), np.ones(n_kp)]).astype(np.float64)
    parts[:, INVISIBLE_KP] = 0.0
    return parts


def _coded_mask(box: tuple[int, int, int, int]) -> np.ndarray:
    """(H, W) bool, the 1-based inclusive box filled."""
    mask = np.zeros((CODED_H, CODED_W), bool)
    mask[box[1] - 1 : box[3], box[0] - 1 : box[2]] = True
    return mask


def _write_coded(image_dir: Path, anno: Path, n_kp: int) -> None:
    """One PNG (lossless: the crops can be compared pixel for pixel) and a MATLAB struct array of one record per
    box of :data:`CODED_BOXES`, in the layout of the real annotation files."""
    (image_dir / "coded").mkdir(parents=True)
    Image.fromarray(_coded_image()).save(image_dir / "coded/img.png")
    records = [
        {
            "id": i,
            "rel_path": "coded/img.png",
            "train": 1,
            "test": 0,
            "bbox": dict(zip(("x1", "y1", "x2", "y2"), map(float, box), strict=True)),
            "width": CODED_W,
            "height": CODED_H,
            "parts": _coded_parts(box, n_kp),
            "mask": _coded_mask(box),
            "class_id": 1,
            "cad_index": 1,
        }
        for i, box in enumerate(CODED_BOXES)
    ]
    write_struct_array(anno, records)


def _coded_cub(root: Path) -> Path:
    """A CUB root of the coded records (split "test")."""
    _write_coded(root / "images", root / "cachedir/cub/data/test_cub_cleaned.mat", len(CUB_KEYPOINTS))
    return root


def _coded_p3d(root: Path) -> Path:
    """A Pascal3D+ root of the coded records (split "train", no point clouds) with a car_kps.mat."""
    _write_coded(root / "Images", root / "ucmr_anno/data/car_train.mat", 12)
    perm = np.array([2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11])  # 1-based, like the real file
    names = np.array([f"kp{i}" for i in range(12)], dtype=object)
    scipy.io.savemat(root / "ucmr_anno/data/car_kps.mat", {"kp_names": names, "kp_perm_inds": perm})
    return root


def _hand_square(box: tuple[int, int, int, int], padding: float) -> tuple[int, int, int]:
    """``(left, top, side)`` of the square crop of a 1-based inclusive box, 0-based: the box one less (CMR's
    reading; UNICORN's reference crops from the 1-based numbers as they are), grown by ``padding`` of its width
    (height) on each side, rounded, the shorter side grown evenly on both sides to the longer (the test boxes leave
    an even difference, where CMR's, the reference's and the loader's rounding agree)."""
    x1, y1, x2, y2 = (c - 1 for c in box)
    bw, bh = x2 - x1 + 1, y2 - y1 + 1
    x1, x2 = round(x1 - padding * bw), round(x2 + padding * bw)
    y1, y2 = round(y1 - padding * bh), round(y2 + padding * bh)
    w, h = x2 - x1 + 1, y2 - y1 + 1
    side = max(w, h)
    assert (side - w) % 2 == 0 and (side - h) % 2 == 0
    return x1 - (side - w) // 2, y1 - (side - h) // 2, side


def test_hand_square_worked_examples() -> None:
    """The hand recipe on the coded boxes, worked out on paper."""
    # (11, 9, 30, 24) -> 0-based (10, 8, 29, 23), 20 x 16, +1 / +0.8 -> (9, 7.2, 30, 23.8) -> (9, 7, 30, 24),
    # 22 x 18 -> rows 2 higher: (9, 5), side 22; padding 0.1: (8, 6.4, 31, 24.6) -> (8, 6, 31, 25) -> (8, 4), 24
    assert _hand_square(CODED_BOXES[0], 0.05) == (9, 5, 22) and _hand_square(CODED_BOXES[0], 0.1) == (8, 4, 24)
    # (1, 1, 20, 28) -> (0, 0, 19, 27), 20 x 28, +1 / +1.4 -> (-1, -1, 20, 28), 22 x 30 -> columns 4 further left
    assert _hand_square(CODED_BOXES[1], 0.05) == (-5, -1, 30)


def _hand_item(
    box: tuple[int, int, int, int], padding: float, img_size: int, mask_size: int, n_kp: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image (S, S, 3) in [0, 1], mask (M, M) and keypoints (K, 3) of the coded record of ``box``, by hand.

    The square crop takes the nearest image pixel outside the image (the mask is zero there) and is resized as the
    reference does, with PIL (bilinear image, nearest mask); a keypoint at 1-based (u, v) is at the 0-based pixel
    (u - 1, v - 1), at (u - 1 - left, v - 1 - top) in the crop, and at ``(c + 0.5) * M / side - 0.5`` in the M-pixel
    mask: pixel centres stay pixel centres, as they do in the resized image (the reference scales ``c`` alone,
    half a pixel off; :func:`_check_keypoints_on_their_pixels` confirms the centres on the image itself).
    """
    left, top, side = _hand_square(box, padding)
    rows, cols = np.arange(top, top + side), np.arange(left, left + side)
    rows_in, cols_in = np.clip(rows, 0, CODED_H - 1), np.clip(cols, 0, CODED_W - 1)
    crop = _coded_image()[rows_in][:, cols_in]
    image = np.asarray(Image.fromarray(crop).resize((img_size, img_size), Image.Resampling.BILINEAR)) / 255.0
    inside = ((rows >= 0) & (rows < CODED_H))[:, None] & ((cols >= 0) & (cols < CODED_W))[None, :]
    mask_crop = Image.fromarray((_coded_mask(box)[rows_in][:, cols_in] & inside).astype(np.uint8) * 255)
    mask = (np.asarray(mask_crop.resize((mask_size, mask_size), Image.Resampling.NEAREST)) > 127).astype(np.float32)
    parts = _coded_parts(box, n_kp)
    keypoints = np.zeros((n_kp, 3))
    for k in np.flatnonzero(parts[2] > 0):
        col, row = parts[0, k] - 1 - left, parts[1, k] - 1 - top
        keypoints[k] = [(col + 0.5) * mask_size / side - 0.5, (row + 0.5) * mask_size / side - 0.5, 1.0]
    return image, mask, keypoints


def _colour_at(image: torch.Tensor, x: float, y: float) -> np.ndarray:
    """(3,) colour of a (3, H, W) image at (column, row) ``(x, y)``, bilinearly between pixel centres, in 0-255."""
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0
    p = image[:, y0 : y0 + 2, x0 : x0 + 2].double().numpy() * 255
    return (1 - fy) * ((1 - fx) * p[:, 0, 0] + fx * p[:, 0, 1]) + fy * ((1 - fx) * p[:, 1, 0] + fx * p[:, 1, 1])


def _check_keypoints_on_their_pixels(item: dict, parts: np.ndarray, source: np.ndarray | None = None) -> None:
    """The image where keypoint k is has the colour of the pixel annotated for keypoint ``source[k]`` (default k):
    the coded image's red and green are a linear ramp, kept by bilinear resizing away from replicated borders."""
    kps = item["keypoints"].double().numpy()
    source = np.arange(len(kps)) if source is None else source
    for k in np.flatnonzero(kps[:, 2] > 0):
        u, v = parts[0, source[k]], parts[1, source[k]]
        red, green, _ = _colour_at(item["image"], kps[k, 0], kps[k, 1])
        assert abs(red - (10 + 4 * (u - 1))) < 0.25 and abs(green - (10 + 4 * (v - 1))) < 0.25, (k, red, green, u, v)


@pytest.mark.parametrize("eval_size", [None, 256])
def test_cub_crops_and_keypoints_match_a_hand_crop(tmp_path: Path, eval_size: int | None) -> None:
    """CUB items of the coded records (padding 0.05) against :func:`_hand_item`, and each keypoint where its
    annotated pixel's colour landed in the image."""
    ds = CUB200(_coded_cub(tmp_path / "cub"), "test", eval_size=eval_size)
    assert not ds.augment and ds.padding == 0.05
    mask_size = eval_size or 64
    for i, box in enumerate(CODED_BOXES):
        item = ds[i]
        _check_item(item, 64, mask_size, 15, hand=_hand_item(box, 0.05, 64, mask_size, 15))
        if eval_size is None:
            _check_keypoints_on_their_pixels(item, _coded_parts(box, 15))


def test_p3d_crops_and_keypoints_match_a_hand_crop(tmp_path: Path) -> None:
    """Pascal3D+ items of the coded records (padding 0.1, the reference's) against :func:`_hand_item`."""
    ds = Pascal3DCar(_coded_p3d(tmp_path / "p3d"), "train", augment=False)
    for i, box in enumerate(CODED_BOXES):
        item = ds[i]
        _check_item(item, 64, 64, 12, hand=_hand_item(box, 0.1, 64, 64, 12))
        _check_keypoints_on_their_pixels(item, _coded_parts(box, 12))


def _flipped_and_plain(ds: CUB200 | Pascal3DCar, index: int) -> dict[bool, dict]:
    """Item ``index`` of an augmenting dataset, once flipped and once not (over torch seeds)."""
    found: dict[bool, dict] = {}
    for seed in range(20):
        torch.manual_seed(seed)
        item = ds[index]
        found.setdefault(bool(item["flipped"]), item)
    assert set(found) == {True, False}
    return found


def _check_hand_flip(
    found: dict[bool, dict], plain: dict, box: tuple[int, int, int, int], padding: float, size: int, pairs: dict
) -> None:
    """A flipped item is the plain one mirrored; its keypoint k is the hand keypoint of k's partner in ``pairs``
    (itself if none) at x' = size - 1 - x, invisible ones (0, 0, 0); it sits on its partner's annotated pixel."""
    n_kp = len(plain["keypoints"])
    source = np.arange(n_kp)
    for a, b in pairs.items():
        source[a], source[b] = b, a
    _, _, hand = _hand_item(box, padding, 64, size, n_kp)
    expected = np.zeros((n_kp, 3))
    for k in range(n_kp):
        if hand[source[k], 2] > 0:
            expected[k] = [size - 1 - hand[source[k], 0], hand[source[k], 1], 1.0]
    flipped = found[True]
    assert torch.equal(found[False]["image"], plain["image"])
    assert torch.equal(found[False]["keypoints"], plain["keypoints"])
    assert torch.equal(flipped["image"], plain["image"].flip(-1))
    assert torch.equal(flipped["mask"], plain["mask"].flip(-1))
    assert np.allclose(flipped["keypoints"].numpy(), expected, atol=1e-4)
    if size == 64:
        _check_keypoints_on_their_pixels(flipped, _coded_parts(box, n_kp), source)


@pytest.mark.parametrize("eval_size", [None, 256])
def test_cub_flip_keeps_keypoints_consistent(tmp_path: Path, eval_size: int | None) -> None:
    """Flipped CUB items (jitter 0: the flip alone) against the hand keypoints with LEye/REye, LLeg/RLeg and
    LWing/RWing swapped, all six visible."""
    root = _coded_cub(tmp_path / "cub")
    parts = _coded_parts(CODED_BOXES[0], 15)
    assert (parts[2, list(CUB_PAIRS) + list(CUB_PAIRS.values())] == 1).all()
    assert all(not np.array_equal(parts[:2, a], parts[:2, b]) for a, b in CUB_PAIRS.items())
    ds = CUB200(root, "test", augment=True, jitter=0.0, eval_size=eval_size)
    plain = CUB200(root, "test", eval_size=eval_size)[0]
    _check_hand_flip(_flipped_and_plain(ds, 0), plain, CODED_BOXES[0], 0.05, eval_size or 64, CUB_PAIRS)


def test_struct_array_quirks(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    recs = [make_record(rng, f"a/{i}.jpg", 40, 30, 15, i) for i in range(2)]
    write_struct_array(tmp_path / "two.mat", recs)
    write_struct_array(tmp_path / "one.mat", recs[:1])  # squeeze_me turns this into a bare struct
    two, one = (
        load_struct_array(tmp_path / "two.mat", "images"),
        load_struct_array(tmp_path / "one.mat", "images"),
    )
    assert len(two) == 2 and len(one) == 1
    assert two[1]["rel_path"] == "a/1.jpg" and set(two[0]["bbox"]) == {"x1", "y1", "x2", "y2"}
    assert two[0]["mask"].dtype == np.uint8 and two[0]["parts"].shape == (3, 15)
    with pytest.raises(KeyError, match="no variable 'sfm_anno'"):
        load_struct_array(tmp_path / "one.mat", "sfm_anno")


@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_cub_items(cub_root: Path, split: str) -> None:
    ds = CUB200(cub_root, split)
    assert len(ds) == {"train": 4, "val": 7, "test": 3}[split]
    for i in range(len(ds)):
        _check_item(ds[i], 64, 64, 15)


def test_cub_eval_size(cub_root: Path) -> None:
    item = CUB200(cub_root, "test", eval_size=256)[0]
    _check_item(item, 64, 256, 15)


def test_cub_jitter_moves_the_crop(cub_root: Path) -> None:
    ds = CUB200(cub_root, "train", augment=True)
    boxes = {tuple(ds.square_crop_box(2, np.random.default_rng(s))) for s in range(5)}
    assert ds.jitter == 0.05 and len(boxes) > 1  # the reference's
    centred = CUB200(cub_root, "train", augment=True, jitter=0.0)
    plain = CUB200(cub_root, "train", augment=False)
    assert {tuple(centred.square_crop_box(2, np.random.default_rng(s))) for s in range(5)} == {
        tuple(plain.square_crop_box(2, None))
    }
    for jitter in (-0.1, 0.5, 0.9):  # from 0.5 on, the corners could cross: a crop of nothing
        with pytest.raises(DatasetError, match=r"^jitter must be in \[0, 0.5\) \(a fraction of the box size\), got"):
            CUB200(cub_root, "train", jitter=jitter)


def test_cub_missing_root_and_annotations(tmp_path: Path, cub_root: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match=r"nowhere.*CUB_200_2011"):
        CUB200(tmp_path / "nowhere")
    (cub_root / "cachedir/cub/data/val_cub_cleaned.mat").unlink()
    with pytest.raises(DatasetNotFoundError, match=r"val_cub_cleaned\.mat.*cachedir"):
        CUB200(cub_root, "val")


def test_cub_bad_image_raise_or_skip(cub_root: Path) -> None:
    ds = CUB200(cub_root, "test")
    bad = ds.image_path(1)
    bad.write_bytes(b"garbage")
    with pytest.raises(ImageLoadError, match=bad.name):
        ds[1]
    skipping = CUB200(cub_root, "test", on_error="skip")
    with pytest.warns(RuntimeWarning, match=bad.name):
        item = skipping[1]
    assert int(item["index"]) == 2 and str(bad) in skipping.bad_files


def test_annotated_images_keep_their_stored_grid(cub_root: Path) -> None:
    # the boxes, masks and keypoints refer to the stored pixels: an orientation tag must not turn the image away
    ds = CUB200(cub_root, "test")
    before = ds[0]
    path = ds.image_path(0)
    save_with_orientation(Image.open(path).copy(), path.with_suffix(".png"), 6)  # PNG: the same pixels, lossless
    ds.records[0]["rel_path"] = str(Path(ds.records[0]["rel_path"]).with_suffix(".png"))
    after = ds[0]
    _check_item(after, 64, 64, 15)
    assert torch.equal(after["image"], before["image"]) and torch.equal(after["mask"], before["mask"])


def test_non_finite_image_is_a_bad_image(cub_root: Path) -> None:
    ds = CUB200(cub_root, "test", on_error="skip")
    Image.fromarray(np.full((40, 60), np.nan, np.float32), "F").save(ds.image_path(1).with_suffix(".tif"))
    ds.records[1]["rel_path"] = str(Path(ds.records[1]["rel_path"]).with_suffix(".tif"))
    with pytest.warns(RuntimeWarning, match=r"\.tif: pixel values are NaN or infinite"):
        item = ds[1]
    assert int(item["index"]) == 2 and torch.isfinite(item["image"]).all()
    ds.on_error = "raise"
    with pytest.raises(ImageLoadError, match=r"\.tif: pixel values are NaN or infinite"):
        ds[1]


def test_p3d_items_and_points(p3d_root: Path) -> None:
    train = Pascal3DCar(p3d_root, "train")
    assert len(train) == 3 and "points" not in train[0]
    for i in range(len(train)):
        _check_item(train[i], 64, 64, 12)
    test = Pascal3DCar(p3d_root, "test")
    assert len(test) == 2
    for i in range(len(test)):
        item = test[i]
        _check_item(item, 64, 64, 12)
        assert item["points"].shape == (200, 3) and item["normals"].shape == (200, 3)
        assert 1 <= int(item["cad_index"]) <= 10
        expected = torch.load(p3d_root / f"unicorn_anno/car/{int(item['cad_index']):02d}_pointcloud.pt")["points"]
        assert torch.equal(item["points"], expected)


def test_p3d_flip_uses_kp_perm(p3d_root: Path, tmp_path: Path) -> None:
    """The permutation is car_kps.mat's, 0-based; a flipped car's keypoints are the hand ones of the pairs it
    lists, mirrored."""
    perm = scipy.io.loadmat(p3d_root / "ucmr_anno/data/car_kps.mat", squeeze_me=True)["kp_perm_inds"] - 1
    ds = Pascal3DCar(p3d_root, "train", augment=True)
    assert np.array_equal(ds.flip_perm, perm)
    root = _coded_p3d(tmp_path / "p3d")
    coded = Pascal3DCar(root, "train", augment=True, jitter=0.0)
    plain = Pascal3DCar(root, "train", augment=False)[1]
    _check_hand_flip(_flipped_and_plain(coded, 1), plain, CODED_BOXES[1], 0.1, 64, P3D_PAIRS)


def test_p3d_missing_files(tmp_path: Path, p3d_root: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match="PASCAL3D"):
        Pascal3DCar(tmp_path / "nowhere")
    (p3d_root / "unicorn_anno/car/07_pointcloud.pt").unlink()
    with pytest.raises(DatasetNotFoundError, match=r"07_pointcloud\.pt.*unicorn_anno"):
        Pascal3DCar(p3d_root, "test")
    (p3d_root / "ucmr_anno/data/car_train.mat").unlink()
    with pytest.raises(DatasetNotFoundError, match=r"car_train\.mat.*UCMR"):
        Pascal3DCar(p3d_root, "train")


# ---------------------------------------------------------------------------------------------- malformed files
def _rewrite(anno: Path, change) -> None:
    """Apply ``change(records)`` to the records of a MATLAB annotation file and write it back."""
    records = load_struct_array(anno, "images")
    change(records)
    keys = sorted({k for r in records for k in r})
    arr = np.empty(len(records), dtype=[(k, "O") for k in keys])
    for i, record in enumerate(records):
        for k in keys:
            arr[i][k] = record.get(k, np.zeros((0, 0)))
    scipy.io.savemat(anno, {"images": arr})


def _set(i: int, key: str, value) -> object:
    def change(records: list[dict]) -> None:
        records[i][key] = value

    return change


def _drop(key: str) -> object:
    def change(records: list[dict]) -> None:
        for record in records:
            del record[key]

    return change


@pytest.mark.parametrize(
    "content",
    [b"hello, not MATLAB\n", b"", "truncated", "folder"],
    ids=["text", "empty", "truncated", "folder"],
)
def test_an_unreadable_annotation_file_is_one_error_naming_it(cub_root: Path, content) -> None:
    anno = cub_root / "cachedir/cub/data/val_cub_cleaned.mat"
    if content == "truncated":
        anno.write_bytes(anno.read_bytes()[:600])
    elif content == "folder":
        anno.unlink()
        anno.mkdir()
    else:
        anno.write_bytes(content)
    with pytest.raises(DatasetError, match=r"cannot read .*val_cub_cleaned\.mat"):
        CUB200(cub_root, "val")


MALFORMED = [
    ("no-box", _drop("bbox"), r"record 1 of .*val_cub_cleaned\.mat: no 'bbox' field"),
    ("box-as-vector", _set(1, "bbox", np.array([1.0, 2.0, 30.0, 40.0])), r"record 2 .*: bbox must be a struct"),
    (
        "inverted-box",
        _set(1, "bbox", {"x1": 40.0, "y1": 40.0, "x2": 5.0, "y2": 5.0}),
        r"record 2 .*: bbox .* must be at least 2 pixels wide and high",
    ),
    (
        "one-pixel-box",
        _set(1, "bbox", {"x1": 9.0, "y1": 9.0, "x2": 9.0, "y2": 9.0}),
        r"record 2 .*: bbox .* at least 2 pixels",
    ),
    (
        "nan-corner",
        _set(1, "bbox", {"x1": float("nan"), "y1": 1.0, "x2": 9.0, "y2": 9.0}),
        r"record 2 .*: bbox's x1, y1, x2, y2 must be finite",
    ),
    ("keypoints-transposed", _set(1, "parts", np.zeros((15, 3))), r"record 2 .*: parts must be \(3, 15\).*\(15, 3\)"),
    ("keypoints-short", _set(1, "parts", np.zeros((3, 10))), r"record 2 .*: parts must be \(3, 15\)"),
    ("mask-vector", _set(1, "mask", np.ones(5, dtype=np.uint8)), r"record 2 .*: mask must be an \(H, W\) array"),
]


@pytest.mark.parametrize("change, message", [c[1:] for c in MALFORMED], ids=[c[0] for c in MALFORMED])
def test_a_malformed_record_is_named_or_left_out_when_skipping(cub_root: Path, change, message) -> None:
    anno = cub_root / "cachedir/cub/data/val_cub_cleaned.mat"
    _rewrite(anno, change)
    with pytest.raises(DatasetError, match=message):
        CUB200(cub_root, "val")
    if "record 2" in message:  # one bad record of 7: skipped with one warning naming it
        with pytest.warns(RuntimeWarning, match=r"skipping 1 of 7 records .*; the first: record 2"):
            skipping = CUB200(cub_root, "val", on_error="skip")
        assert len(skipping) == 6
        _check_item(skipping[1], 64, 64, len(CUB_KEYPOINTS))
    else:  # every record bad: nothing left to skip to
        with pytest.raises(DatasetError, match=r"7 of its 7 records are malformed"):
            CUB200(cub_root, "val", on_error="skip")


def test_an_annotation_file_without_records_is_refused(cub_root: Path) -> None:
    anno = cub_root / "cachedir/cub/data/val_cub_cleaned.mat"
    scipy.io.savemat(anno, {"images": np.empty((0, 0))})
    with pytest.raises(DatasetError, match=r"val_cub_cleaned\.mat holds no records"):
        CUB200(cub_root, "val")


def _mask_of_its_transpose(records: list[dict]) -> None:
    records[1]["mask"] = np.ascontiguousarray(np.asarray(records[1]["mask"]).T)


def _box_off_the_image(records: list[dict]) -> None:
    w = float(records[1]["width"])
    records[1]["bbox"] = {"x1": w + 10, "y1": 1.0, "x2": w + 60, "y2": 40.0}


def _box_a_million_wide(records: list[dict]) -> None:
    records[1]["bbox"] = {"x1": 1.0, "y1": 1.0, "x2": 1e6, "y2": 1e6}


@pytest.mark.parametrize(
    "change, message",
    [
        (_mask_of_its_transpose, r"its mask is (\d+) x (\d+) \(H x W\), the image \2 x \1"),
        (_box_off_the_image, r"its box \(0-based\) .* lies outside the \d+ x \d+ image"),
        (_box_a_million_wide, r"its box makes a crop of \d+ x \d+ pixels, over the image limit"),
    ],
    ids=["mask-transposed", "box-off-the-image", "box-too-large"],
)
def test_annotations_that_do_not_fit_their_image_are_a_bad_item(cub_root: Path, change, message) -> None:
    _rewrite(cub_root / "cachedir/cub/data/val_cub_cleaned.mat", change)
    ds = CUB200(cub_root, "val")
    with pytest.raises(ImageLoadError, match=rf"bad annotations for .*{ds.image_path(1).name}: {message}"):
        ds[1]
    skipping = CUB200(cub_root, "val", on_error="skip")
    with pytest.warns(RuntimeWarning, match="bad annotations"):
        assert int(skipping[1]["index"]) == 2


@pytest.mark.parametrize(
    "cad_index, message",
    [
        (0, r"cad_index must be in \[1, 10\] .* got 0"),
        (11, r"cad_index .* got 11"),
        (2.5, r"cad_index must be a whole"),
    ],
)
def test_p3d_cad_index_out_of_the_ten_models_is_named(p3d_root: Path, cad_index, message) -> None:
    _rewrite(p3d_root / "ucmr_anno/data/car_test.mat", _set(0, "cad_index", cad_index))
    with pytest.raises(DatasetError, match=rf"record 1 of .*car_test\.mat: {message}"):
        Pascal3DCar(p3d_root, "test")


@pytest.mark.parametrize(
    "perm, message",
    [
        (np.arange(1, 9), r"parts must be \(3, 8\) .* the 8 keypoints of the flip permutation\), got \(3, 12\)"),
        (np.array([1, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10]), r"flip permutation must hold each index 0\.\.11 once"),
        (None, r"car_kps\.mat has no variable 'kp_perm_inds' \(it has \['kp_names'\]\)"),
        (np.array([2.5, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11]), r"car_kps\.mat: kp_perm_inds must be whole numbers"),
    ],
    ids=["too-short", "zero-based", "missing", "fractional"],
)
def test_p3d_keypoint_permutation_is_checked(p3d_root: Path, perm, message) -> None:
    kps = p3d_root / "ucmr_anno/data/car_kps.mat"
    content = {"kp_names": np.array([f"kp{i}" for i in range(12)], dtype=object)}
    scipy.io.savemat(kps, content if perm is None else {**content, "kp_perm_inds": perm})
    with pytest.raises(DatasetError, match=message):
        Pascal3DCar(p3d_root, "train")


@pytest.mark.parametrize(
    "content, message",
    [
        (b"garbage", r"cannot read the CAD point cloud .*03_pointcloud\.pt"),
        ({"points": torch.zeros(5, 3)}, r"must hold 'points' and 'normals', got \['points'\]"),
        ({"points": torch.zeros(5, 2), "normals": torch.zeros(5, 3)}, r"must hold \(P, 3\) points and normals"),
        (
            {"points": torch.full((5, 3), float("nan")), "normals": torch.zeros(5, 3)},
            r"03_pointcloud\.pt: points and normals must be as many and finite",
        ),
        (
            {"points": torch.zeros(5, 3), "normals": torch.zeros(7, 3)},
            r"must be as many and finite, got \{'points': 5, 'normals': 7\}",
        ),
        ("deflated", r"cannot read the CAD point cloud \S+03_pointcloud\.pt: its entry '\S+' is compressed"),
    ],
    ids=["garbage", "no-normals", "2d-points", "nan-points", "more-normals", "deflated"],
)
def test_p3d_bad_point_cloud_is_named(p3d_root: Path, content, message) -> None:
    path = p3d_root / "unicorn_anno/car/03_pointcloud.pt"
    if content == "deflated":
        deflated_torch_file({"points": torch.zeros(5, 3), "normals": torch.zeros(5, 3)}, path)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save(content, path)
    with pytest.raises(DatasetError, match=message):
        Pascal3DCar(p3d_root, "test")
