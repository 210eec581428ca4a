"""Folder, CompCars and LSUN (LMDB) loaders."""

from __future__ import annotations

import io
import os
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.support.datasets import save_with_orientation, write_lsun, write_photo
from unicorn.data.folder import CompCars, ImageFolder, UnreadableFolderWarning, list_images
from unicorn.data.framing import fit_and_pad
from unicorn.data.images import DatasetError, DatasetNotFoundError, ImageLoadError
from unicorn.errors import MissingPackageError, UserError


def _check_item(item: dict, size: int = 64) -> None:
    assert item["image"].shape == (3, size, size) and item["image"].dtype == torch.float32
    assert 0 <= item["image"].min() and item["image"].max() <= 1
    assert item["mask"].shape == (1, size, size) and not item["has_mask"] and not item["has_pose"]
    assert torch.equal(item["R"], torch.eye(3)) and torch.allclose(item["T"], torch.tensor([0.0, 0.0, 2.732]))


@pytest.fixture
def mixed_folder(tmp_path: Path) -> Path:
    """Images of every mode and a few sizes, one nested, plus a non-image file."""
    root = tmp_path / "photos"
    rng = np.random.default_rng(0)
    rgb = Image.fromarray(rng.integers(0, 256, (30, 50, 3), dtype=np.uint8))
    root.mkdir()
    rgb.convert("L").save(root / "gray.png")
    rgb.convert("RGBA").save(root / "rgba.png")
    rgb.convert("P").save(root / "palette.png")
    Image.fromarray(rng.integers(0, 65536, (40, 20)).astype(np.uint16)).save(root / "deep.png")
    (root / "sub" / "deeper").mkdir(parents=True)
    rgb.save(root / "sub" / "deeper" / "photo.JPG")
    (root / "notes.txt").write_text("not an image")
    return root


def test_folder_reads_every_mode(mixed_folder: Path) -> None:
    ds = ImageFolder(mixed_folder, img_size=32)
    assert len(ds) == 5  # the .txt is ignored, the nested upper-case .JPG is found
    for i in range(len(ds)):
        _check_item(ds[i], 32)


@pytest.mark.parametrize("extensions", [["PNG"], "png", (".png",), ["png", ".jpg"]])
def test_folder_suffixes_with_or_without_their_dot(mixed_folder: Path, extensions: object) -> None:
    """``dataset.options.extensions=[png]`` in a config picks the PNGs, as ``.png`` does."""
    names = {p.name for p in ImageFolder(mixed_folder, extensions=extensions).files}
    pngs = {"gray.png", "rgba.png", "palette.png", "deep.png"}
    assert names == (pngs | {"photo.JPG"} if ".jpg" in extensions else pngs)


def test_folder_flip_augmentation(mixed_folder: Path) -> None:
    ds, plain = ImageFolder(mixed_folder, augment=True), ImageFolder(mixed_folder)
    ref = plain[0]["image"]
    outs = set()
    for seed in range(12):
        torch.manual_seed(seed)
        img = ds[0]["image"]
        outs.add("flip" if torch.equal(img, ref.flip(-1)) else "same" if torch.equal(img, ref) else "other")
    assert outs == {"flip", "same"}


def test_folder_errors(tmp_path: Path, mixed_folder: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match="missing_dir"):
        ImageFolder(tmp_path / "missing_dir")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetNotFoundError, match="empty"):
        ImageFolder(tmp_path / "empty")
    (tmp_path / "photo.png").write_bytes(b"")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning from walking a file as a folder
        with pytest.raises(DatasetError, match=r"photo\.png is a file, not a folder of images"):
            ImageFolder(tmp_path / "photo.png")
    (mixed_folder / "aaa_broken.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ImageLoadError, match="aaa_broken.png"):
        ImageFolder(mixed_folder)[0]
    with pytest.warns(RuntimeWarning, match="aaa_broken.png"):
        item = ImageFolder(mixed_folder, on_error="skip")[0]
    assert int(item["index"]) == 1


def test_compcars(tmp_path: Path) -> None:
    root = tmp_path / "comp_cars"
    for i, (w, h) in enumerate([(80, 50), (50, 80), (64, 64)]):
        write_photo(root / "images" / f"{i:06d}.jpg", w, h, i)
    write_photo(root / "images" / "extra" / "nested.jpg", 30, 20, 9)
    write_photo(root / "images" / "ignored.png", 30, 20, 9)
    ds = CompCars(root)
    assert len(ds) == 4 and ds.files[0].name == "000000.jpg"
    for i in range(len(ds)):
        _check_item(ds[i])
    with pytest.raises(DatasetNotFoundError, match=r"comp_cars2.*comprehensive_cars"):
        CompCars(tmp_path / "comp_cars2")


def test_lsun_without_lmdb_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from unicorn.data.lsun import LSUN

    monkeypatch.setitem(sys.modules, "lmdb", None)  # makes `import lmdb` fail
    with pytest.raises(MissingPackageError, match=r"pip install lmdb \(or, in a checkout of unicorn: pip") as info:
        LSUN(tmp_path, "horse")
    assert isinstance(info.value, ImportError) and isinstance(info.value, UserError)  # a one-line error in the CLIs


def test_lsun_indices_file(tmp_path: Path) -> None:
    from unicorn.data.lsun import read_lsun_indices

    (tmp_path / "indices.txt").write_text("0 3\n1 7\n2 8\n")
    assert read_lsun_indices(tmp_path / "indices.txt").tolist() == [3, 7, 8]
    (tmp_path / "indices.txt").write_text("# j k\n0 3\n\n1 7  # kept\r\n")  # comments, blank lines, CRLF
    assert read_lsun_indices(tmp_path / "indices.txt").tolist() == [3, 7]
    (tmp_path / "indices.txt").write_bytes(b"\xef\xbb\xbf0 3\r\n1 7\r\n")  # a byte-order mark first
    assert read_lsun_indices(tmp_path / "indices.txt").tolist() == [3, 7]


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"j k\n0 3\n", "line 1 of .*: expected two integers '<j> <k>', got 'j k'"),
        (b"0 3\n1\n2 8\n", "line 2 of .*: expected two integers '<j> <k>', got '1'"),
        (b"0 3\n1 7 9\n", "line 2 of .*, got '1 7 9'"),
        (b"0,3\n", "line 1 of .*, got '0,3'"),
        (b"0 3.5\n", "line 1 of .*, got '0 3.5'"),
        (b"0 3\n# caf\xe9\n", "line 2 of .*: not UTF-8 text"),
        (b"", "lists no indices"),
        (b"\n# nothing\n", "lists no indices"),
    ],
    ids=["header", "ragged", "three-columns", "commas", "float", "latin-1", "empty", "comments-only"],
)
def test_lsun_malformed_indices_name_the_file_and_line(tmp_path: Path, content: bytes, problem: str) -> None:
    from unicorn.data.lsun import read_lsun_indices

    (tmp_path / "indices.txt").write_bytes(content)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warned about an empty file before failing
        with pytest.raises(DatasetError, match=problem) as info:
            read_lsun_indices(tmp_path / "indices.txt")
    assert "indices.txt" in str(info.value)


def test_lsun_reads_lmdb_and_cleaned_subset(tmp_path: Path) -> None:
    from unicorn.data.lsun import LSUN

    keys = write_lsun(tmp_path, "horse", 24)
    (tmp_path / "horse" / "indices.txt").write_text("".join(f"{j} {k}\n" for j, k in enumerate(range(0, 24, 2))))
    ds = LSUN(tmp_path, "horse", cleaned=True, augment=True)
    assert len(ds) == 12 and ds.keys[1] == keys[2]
    for i in range(len(ds)):
        _check_item(ds[i])
    # worker processes open their own LMDB handle
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=1)))
    assert batch["image"].shape == (4, 3, 64, 64)
    full = LSUN(tmp_path, "horse", cleaned=False)
    assert len(full) == 25
    with pytest.raises(ImageLoadError, match="ffff_corrupt"):
        full[24]
    with pytest.raises(DatasetNotFoundError, match="indices.txt"):
        (tmp_path / "horse" / "indices.txt").unlink()
        LSUN(tmp_path, "horse", cleaned=True)


def _edged(width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 grey with a red left column, a blue right one, a green top row and a yellow bottom row."""
    image = np.full((height, width, 3), 128, np.uint8)
    image[:, 0], image[:, -1] = (255, 0, 0), (0, 0, 255)
    image[0], image[-1] = (0, 255, 0), (255, 255, 0)
    return image


def _hand_lsun(image: np.ndarray, size: int = 64, padding: float = 0.1) -> np.ndarray:
    """(size, size, 3) in [0, 1]: the whole image grown by ``padding`` of its width (height) on each side with its
    border pixels repeated, resized (PIL, 8 bits, as the reference) so its longer side is ``size``, centred, and
    the shorter side filled by repeating its first and last rows (columns)."""
    H, W = image.shape[:2]
    dx, dy = round(padding * W), round(padding * H)
    crop = image[np.clip(np.arange(-dy, H + dy), 0, H - 1)][:, np.clip(np.arange(-dx, W + dx), 0, W - 1)]
    h, w = crop.shape[:2]
    nh, nw = round(h * size / max(h, w)), round(w * size / max(h, w))
    resized = np.asarray(Image.fromarray(crop).resize((nw, nh), Image.Resampling.BILINEAR)) / 255.0
    top, left = (size - nh) // 2, (size - nw) // 2
    return np.pad(resized, [(top, size - nh - top), (left, size - nw - left), (0, 0)], mode="edge")


def test_lsun_frames_the_whole_image_by_hand(tmp_path: Path) -> None:
    """A wide and a tall record with coloured edges (PNG values, lossless), not augmenting: each item against
    :func:`_hand_lsun`, and the wide one's edges where they land by hand: its 40 x 20 pixels padded by 4 and 2 make
    48 x 24, scaled by 4/3 to 64 x 32 at rows 16..47; the 4 repeated + 1 red columns fill columns 0..5, the 2 + 1
    green rows 16..18 (and the 16 pad rows above), the yellow ones 45..47 and the pad rows below."""
    lmdb = pytest.importorskip("lmdb", reason="the optional 'lmdb' package is not installed")
    from unicorn.data.lsun import LSUN

    images = {b"a_wide": _edged(40, 20), b"b_tall": _edged(20, 30)}
    (tmp_path / "horse").mkdir()
    env = lmdb.open(str(tmp_path / "horse"), map_size=1 << 22)
    with env.begin(write=True) as txn:
        for key, image in images.items():
            buf = io.BytesIO()
            Image.fromarray(image).save(buf, format="PNG")
            txn.put(key, buf.getvalue())
    env.close()
    ds = LSUN(tmp_path, "horse", cleaned=False, augment=False)
    assert ds.keys == list(images) and ds.padding == 0.1
    items = [ds[i] for i in range(len(ds))]
    for item, image in zip(items, images.values(), strict=True):
        _check_item(item)
        assert np.abs(item["image"].permute(1, 2, 0).numpy() - _hand_lsun(image)).max() <= 1.0 / 255
    wide = items[0]["image"].permute(1, 2, 0).numpy()
    red, grey = np.array([1.0, 0.0, 0.0]), np.full(3, 128 / 255)
    assert np.allclose(wide[22:42, :6], red, atol=1e-4) and not np.allclose(wide[22:42, 6], red, atol=0.1)
    assert np.allclose(wide[22:42, 10:54], grey, atol=1e-4)
    assert np.allclose(wide[:19], [0.0, 1.0, 0.0], atol=1e-4) and np.allclose(wide[45:], [1.0, 1.0, 0.0], atol=1e-4)
    assert np.array_equal(wide[:16], np.broadcast_to(wide[16], (16, 64, 3)))  # pad rows repeat the border row
    assert np.array_equal(wide[48:], np.broadcast_to(wide[47], (16, 64, 3)))
    assert not np.allclose(wide[16], wide[19], atol=0.1) and not np.allclose(wide[44], wide[47], atol=0.1)


@pytest.mark.parametrize("damage", ["empty", "random", "truncated"])
def test_lsun_corrupt_lmdb_is_one_error_naming_it(tmp_path: Path, damage: str) -> None:
    from unicorn.data.lsun import LSUN

    write_lsun(tmp_path, "horse", 4)
    data = tmp_path / "horse" / "data.mdb"
    size = data.stat().st_size
    # a truncated file would kill the process with SIGBUS on the first read past its end, were it not refused
    content = {
        "empty": b"",
        "random": np.random.default_rng(0).bytes(size),
        "truncated": data.read_bytes()[: size // 3],
    }
    data.write_bytes(content[damage])
    with pytest.raises(DatasetError, match=re.escape(f"cannot read the LMDB in {tmp_path / 'horse'}: ")) as info:
        LSUN(tmp_path, "horse", cleaned=False)
    assert "\n" not in str(info.value)


def test_lsun_unreadable_record_is_skipped_like_a_bad_image(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import unicorn.data.lsun as lsun

    lmdb = pytest.importorskip("lmdb", reason="the optional 'lmdb' package is not installed")
    write_lsun(tmp_path, "horse", 4)
    ds = lsun.LSUN(tmp_path, "horse", cleaned=False)
    real = lsun._open_env(ds.path)

    class CorruptFirstRecord:  # an environment whose first record lies on a corrupt page
        def begin(self, write: bool = False) -> CorruptFirstRecord:
            return self

        def __enter__(self) -> CorruptFirstRecord:
            return self

        def __exit__(self, *exc: object) -> None:
            return None

        def get(self, key: bytes) -> bytes | None:
            if key == ds.keys[0]:
                raise lmdb.CorruptedError("MDB_CORRUPTED: Located page was wrong type")
            with real.begin() as txn:
                return txn.get(key)

    monkeypatch.setattr(lsun, "_open_env", lambda path: CorruptFirstRecord())
    with pytest.raises(ImageLoadError, match=rf"{ds.keys[0].decode()}\]: CorruptedError: MDB_CORRUPTED"):
        ds[0]
    ds.on_error = "skip"
    with pytest.warns(RuntimeWarning, match=ds.keys[0].decode()):
        assert int(ds[0]["index"]) == 1


def test_unicorn_data_check_reads_an_lsun_config_name_as_its_tag(tmp_path: Path, capsys) -> None:
    from unicorn.cli.data import main

    write_lsun(tmp_path, "motorbike", 3)  # and a fourth record that is not an image
    (tmp_path / "motorbike" / "indices.txt").write_text("".join(f"{j} {j}\n" for j in range(4)))
    # lsun_motorbike, as dataset=lsun_motorbike names it, is the lsun loader with --tag motorbike
    assert main(["check", "lsun_motorbike", "--root", str(tmp_path), "--split", "train", "--all"]) == 1
    out = capsys.readouterr().out
    assert out.startswith("lsun_motorbike train: 4 items") and "3 readable, 1 not" in out
    assert main(["check", "lsun_horse", "--root", str(tmp_path)]) == 2
    assert str(tmp_path / "horse") in capsys.readouterr().err
    assert main(["check", "lsun", "--tag", "motorbike", "--root", str(tmp_path), "--split", "train"]) == 0
    assert capsys.readouterr().out.startswith("lsun train: 4 items")


@pytest.mark.parametrize(
    "args, message",
    [
        (["lsun"], "lsun needs --tag, the LSUN category whose folder is under --root (horse, motorbike), or check "
         "lsun_horse / lsun_motorbike"),  # not horse, silently
        (["lsun_horse", "--tag", "motorbike"], "lsun_horse is lsun with --tag horse, not motorbike: drop --tag, or "
         "check lsun --tag motorbike"),
        (["synthetic", "--tag", "horse"], "--tag is for lsun only (the LSUN category), not synthetic"),
        (["folder", "--tag", "horse"], "--tag is for lsun only (the LSUN category), not folder"),
        (["lsun_motorbike", "--categories", "car"], "--categories picks ShapeNet or synthetic categories; lsun has "
         "none: drop --categories"),  # not ignored, silently
        (["folder", "--categories"], "--categories picks ShapeNet or synthetic categories; folder has none: drop "
         "--categories"),
    ],
)  # fmt: skip
def test_unicorn_data_check_refuses_an_option_it_would_not_use(
    tmp_path: Path, capsys, args: list[str], message
) -> None:
    from unicorn.cli.data import main

    write_lsun(tmp_path, "motorbike", 3)  # refused before anything is read
    assert main(["check", *args, "--root", str(tmp_path)]) == 2
    assert capsys.readouterr().err == f"unicorn-data: error: {message}\n"


def test_lsun_missing_root(tmp_path: Path) -> None:
    pytest.importorskip("lmdb", reason="the optional 'lmdb' package is not installed")
    from unicorn.data.lsun import LSUN

    with pytest.raises(DatasetNotFoundError, match=r"motorbike.*dl\.yf\.io"):
        LSUN(tmp_path, "motorbike")


def test_lsun_framing_options_that_would_leave_nothing_are_refused(tmp_path: Path) -> None:
    """Padding down to -0.49 (the 32 x 40 and 48 x 32 images shrunk past their centre) keeps a pixel of each image;
    -0.5 and beyond, or a jitter of 0.5 and more (whose corners could cross), are refused when the dataset is made."""
    pytest.importorskip("lmdb", reason="the optional 'lmdb' package is not installed")
    from unicorn.data.lsun import LSUN

    write_lsun(tmp_path, "horse", 2)
    ds = LSUN(tmp_path, "horse", cleaned=False, padding=-0.49)
    for i in range(2):
        _check_item(ds[i])
    with pytest.raises(DatasetError, match=r"^padding must be > -0.5 \(a fraction of the image size added"):
        LSUN(tmp_path, "horse", cleaned=False, padding=-0.5)
    with pytest.raises(DatasetError, match=r"^jitter must be in \[0, 0.5\) \(a fraction of the image size\), got"):
        LSUN(tmp_path, "horse", cleaned=False, jitter=0.5)


def test_decompression_bomb_is_skipped_like_any_bad_image(mixed_folder: Path) -> None:
    from tests.support.datasets import bomb_png

    bomb_png(mixed_folder / "aaa_bomb.png")
    with pytest.raises(ImageLoadError, match="aaa_bomb.png.*exceeds the limit"):
        ImageFolder(mixed_folder)[0]
    with pytest.warns(RuntimeWarning, match="aaa_bomb.png"):
        item = ImageFolder(mixed_folder, on_error="skip")[0]
    assert int(item["index"]) == 1


def test_folder_photos_are_upright_by_their_exif_orientation(tmp_path: Path) -> None:
    stored = np.zeros((16, 32, 3), np.uint8)  # stored 32 wide, 16 high: shown 16 wide, 32 high
    stored[:, :8] = 255  # on top once shown
    save_with_orientation(Image.fromarray(stored), tmp_path / "photos" / "phone.png", 6)
    image = ImageFolder(tmp_path / "photos", img_size=32)[0]["image"]
    expected = fit_and_pad(np.rot90(stored, k=-1).astype(np.float32) / 255, 32)
    np.testing.assert_allclose(image.permute(1, 2, 0).numpy(), expected, atol=1e-6)
    assert image[:, :4].min() == 1.0 and image[:, -4:].max() == 0.0  # white on top, black at the bottom


def test_non_finite_image_is_skipped_like_any_bad_image(mixed_folder: Path) -> None:
    Image.fromarray(np.full((8, 8), np.nan, np.float32), "F").save(mixed_folder / "aaa_nan.tif")
    with pytest.raises(ImageLoadError, match="aaa_nan.tif: pixel values are NaN or infinite"):
        ImageFolder(mixed_folder)[0]
    with pytest.warns(RuntimeWarning, match="aaa_nan.tif"):
        item = ImageFolder(mixed_folder, on_error="skip")[0]
    assert int(item["index"]) == 1 and torch.isfinite(item["image"]).all()


def _symlink(link: Path, target: str | Path) -> None:
    try:
        link.symlink_to(target)
    except (OSError, NotImplementedError):
        pytest.skip("symbolic links are not available here")


def test_folder_follows_linked_folders_once(tmp_path: Path) -> None:
    store, root = tmp_path / "store", tmp_path / "photos"
    write_photo(store / "more" / "b.jpg", 20, 10, 0)
    write_photo(root / "a.jpg", 20, 10, 1)
    _symlink(root / "more", store / "more")  # Path.rglob did not go into linked folders: b.jpg went missing
    _symlink(root / "again", store / "more")  # the same folder by another route: read once, by the first route
    _symlink(root / "self", ".")  # loops back up the tree
    expected = [root / "a.jpg", root / "again" / "b.jpg"]
    assert list_images(root) == expected and ImageFolder(root).files == expected


def test_folder_leaves_out_the_output_folders_of_unicorns_commands(tmp_path: Path) -> None:
    root = tmp_path / "photos"
    write_photo(root / "a.jpg", 20, 10, 0)
    for folder, records in {"rec": ["reconstructions.json"], "ev": ["metrics.json", "per_image.csv"]}.items():
        write_photo(root / folder / "report" / "sample00_input.png", 20, 10, 1)  # an output's pictures
        for name in records:
            (root / folder / name).write_text("{}")
    write_photo(root / "notes" / "b.jpg", 20, 10, 2)
    (root / "notes" / "metrics.json").write_text("{}")  # one record of unicorn-eval's two: a folder of photos
    expected = [root / "a.jpg", root / "notes" / "b.jpg"]
    assert list_images(root) == expected and ImageFolder(root).files == expected


def test_a_folder_that_cannot_be_read_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = tmp_path / "photos"
    write_photo(root / "a.jpg", 20, 10, 1)
    write_photo(root / "locked" / "b.jpg", 20, 10, 2)
    scandir, stat = os.scandir, os.stat

    # as a folder without read and search permission (the tests may run as root, who reads all): neither its list
    # nor anything in it (a record that would make it an output folder) can be read
    def no_permission(path):
        if Path(path).name == "locked":
            raise PermissionError(13, "Permission denied", str(path))
        return scandir(path)

    def no_search(path, *args, **kwargs):
        if Path(path).parent.name == "locked":
            raise PermissionError(13, "Permission denied", str(path))
        return stat(path, *args, **kwargs)

    monkeypatch.setattr(os, "scandir", no_permission)
    monkeypatch.setattr(os, "stat", no_search)
    with pytest.warns(
        UnreadableFolderWarning, match=r"cannot read the folder .*locked: Permission denied; the images in it"
    ):
        assert list_images(root) == [root / "a.jpg"]


def test_folder_lists_broken_image_links_as_bad_images(tmp_path: Path) -> None:
    root = tmp_path / "photos"
    write_photo(root / "a.jpg", 20, 10, 1)
    _symlink(root / "b_dangling.jpg", "nowhere.jpg")
    _symlink(root / "c_loop.jpg", "c_loop.jpg")
    if hasattr(os, "mkfifo"):
        os.mkfifo(root / "d_pipe.jpg")  # not a file: not listed (reading it would block)
    ds = ImageFolder(root)
    assert [p.name for p in ds.files] == ["a.jpg", "b_dangling.jpg", "c_loop.jpg"]
    for i, name in ((1, "b_dangling.jpg"), (2, "c_loop.jpg")):
        with pytest.raises(ImageLoadError, match=name):
            ds[i]
    skipping = ImageFolder(root, on_error="skip")
    with pytest.warns(RuntimeWarning) as record:
        assert int(skipping[1]["index"]) == 0  # both links skipped, on to a.jpg
    messages = [str(w.message) for w in record]
    assert len(messages) == 2 and "b_dangling.jpg" in messages[0] and "c_loop.jpg" in messages[1]
