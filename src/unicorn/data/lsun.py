"""LSUN objects (horse, motorbike) read from their LMDB, optionally restricted to UNICORN's cleaned subset.

Expected layout (``root`` = ``datasets/lsun``)::

    <tag>/data.mdb, <tag>/lock.mdb   # the LMDB of http://dl.yf.io/lsun/objects/<tag>.zip, values = JPEG bytes
    <tag>/indices.txt                # UNICORN's cleaned subset: lines "<j> <k>", k = index of the kept key
                                     #   in LMDB key order

Reading needs the optional ``lmdb`` package (``pip install unicorn3d[lmdb]``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from unicorn.data.common import OnError, UnicornDataset, item_rng
from unicorn.data.folder import unannotated_item
from unicorn.data.framing import crop_box, jitter_bbox, pad_bbox
from unicorn.data.images import DatasetError, ImageLoadError, decode_image, require
from unicorn.errors import MissingPackageError

__all__ = ["LSUN", "import_lmdb", "read_lsun_indices"]

_HINT = (
    "Download the LSUN object LMDB with `python download.py -c <tag>` from github.com/fyu/lsun (or "
    "http://dl.yf.io/lsun/objects/<tag>.zip), unzip it to <root>/<tag>/, and put UNICORN's cleaned index "
    "list indices.txt (from UNICORN's data download) in the same folder."
)


def import_lmdb() -> Any:
    """Import the optional ``lmdb`` package, with an install hint when it is missing."""
    try:
        import lmdb
    except ImportError as err:
        raise MissingPackageError(
            "the LSUN loader reads LMDB databases and needs the optional 'lmdb' package: "
            "pip install unicorn3d[lmdb]  (or: pip install lmdb)"
        ) from err
    return lmdb


# py-lmdb refuses to open one environment twice in a process, and handles must not be used across a fork
# (DataLoader workers): keep one read-only environment per path, reopened in each new process
_ENVS: dict[str, tuple[int, Any]] = {}


def _open_env(path: Path) -> Any:
    key = str(path.resolve())
    pid, env = _ENVS.get(key, (None, None))
    if pid != os.getpid():
        if env is not None:
            env.close()  # the parent's handle, inherited by fork: release this process's copy, then reopen
        env = import_lmdb().open(key, readonly=True, lock=False, readahead=False, meminit=False)
        _ENVS[key] = (os.getpid(), env)
    return env


def read_lsun_indices(path: str | Path) -> np.ndarray:
    """Second column of UNICORN's ``indices.txt`` (space-separated integer pairs, no header) as (N,) int64."""
    table = np.loadtxt(path, dtype=np.int64, ndmin=2)
    if table.shape[1] < 2:
        raise DatasetError(f"{path}: expected lines of two integers '<j> <k>', got {table.shape[1]} column(s)")
    return table[:, 1]


class LSUN(UnicornDataset):
    """LSUN object images (e.g. horses, motorbikes) from an LMDB.

    Each image (upright by its EXIF orientation: nothing is annotated on its pixel grid) is read whole: its full
    frame is enlarged by ``padding`` of its size on every side (jittered by ``jitter`` when
    augmenting), cropped with border replication, then fitted into a square of ``img_size`` and padded.

    Args:
        root: folder holding one LMDB folder per tag.
        tag: category, e.g. ``"horse"`` or ``"motorbike"``.
        cleaned: keep only the keys listed in ``<tag>/indices.txt`` (UNICORN's filtered subset).
        img_size: side of the returned square images.
        augment: box jitter and random horizontal flips (training).
        padding: fraction of the image size added on every side (0.1 in the reference).
        jitter: fraction of the image size by which boxes move when augmenting (0.1).
        on_error: ``"raise"`` or ``"skip"`` undecodable records.

    Items: ``image`` (3, S, S), ``mask`` (1, S, S) of ones (``has_mask`` False), dummy pose.
    """

    def __init__(
        self,
        root: str | Path,
        tag: str = "horse",
        cleaned: bool = True,
        img_size: int = 64,
        augment: bool = False,
        padding: float = 0.1,
        jitter: float = 0.1,
        on_error: OnError = "raise",
    ) -> None:
        super().__init__(on_error)
        if not 0.0 <= jitter < 1.0:
            raise DatasetError(f"jitter must be in [0, 1) (a fraction of the image size), got {jitter}")
        import_lmdb()  # fail early, with the install hint
        root = require(root, "LSUN root", _HINT)
        self.path = require(root / tag, f"LSUN '{tag}' LMDB folder", _HINT)
        require(self.path / "data.mdb", f"LSUN '{tag}' LMDB file", _HINT)
        self.tag, self.img_size, self.augment = tag, int(img_size), bool(augment)
        self.padding, self.jitter = float(padding), float(jitter)
        # keys are read once, in LMDB (byte-sorted) order, the order indices.txt refers to
        with _open_env(self.path).begin(write=False) as txn:
            keys = [bytes(k) for k in txn.cursor().iternext(keys=True, values=False)]
        if cleaned:
            indices_file = require(self.path / "indices.txt", f"LSUN '{tag}' cleaned index list", _HINT)
            indices = read_lsun_indices(indices_file)
            bad = indices[(indices < 0) | (indices >= len(keys))]
            if bad.size:
                raise DatasetError(f"{indices_file}: indices {bad[:5].tolist()} outside the {len(keys)} LMDB keys")
            keys = [keys[k] for k in indices]
        self.keys = keys

    def __len__(self) -> int:
        return len(self.keys)

    def load(self, index: int) -> dict[str, Any]:
        key = self.keys[index]
        name = f"{self.path}[{key.decode(errors='replace')}]"
        with _open_env(self.path).begin(write=False) as txn:
            data = txn.get(key)
        if data is None:
            raise ImageLoadError(name, "key missing from the LMDB")
        image = decode_image(data, name)
        H, W = image.shape[:2]
        rng = item_rng() if self.augment else None
        bbox = pad_bbox(np.array([0.0, 0.0, W - 1.0, H - 1.0]), self.padding)
        if rng is not None and self.jitter > 0:
            bbox = jitter_bbox(bbox, self.jitter, rng)
        image, _ = crop_box(image, np.round(bbox).astype(np.int64))
        flip = rng is not None and rng.random() < 0.5
        return unannotated_item(image, self.img_size, flip)
