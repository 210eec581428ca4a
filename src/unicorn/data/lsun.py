"""LSUN objects (horse, motorbike) read from their LMDB, optionally restricted to UNICORN's cleaned subset.

Expected layout (``root`` = ``datasets/lsun``)::

    <tag>/data.mdb, <tag>/lock.mdb   # the LMDB of http://dl.yf.io/lsun/objects/<tag>.zip, values = JPEG bytes
    <tag>/indices.txt                # UNICORN's cleaned subset: lines "<j> <k>", k = index of the kept key
                                     #   in LMDB key order

Reading needs the optional ``lmdb`` package (``pip install lmdb``; in a checkout: ``pip install -e '.[lmdb]'``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from unicorn.data.common import OnError, UnicornDataset, item_rng
from unicorn.data.folder import unannotated_item
from unicorn.data.framing import crop_box, jitter_bbox, pad_bbox
from unicorn.data.images import DatasetError, ImageLoadError, decode_image, read_text, require
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
            "pip install lmdb (or, in a checkout of unicorn: pip install -e '.[lmdb]')"
        ) from err
    return lmdb


# py-lmdb refuses to open one environment twice in a process, and handles must not be used across a fork
# (DataLoader workers): keep one read-only environment per path, reopened in each new process
_ENVS: dict[str, tuple[int, Any]] = {}


def _lmdb_error(path: Path, err: Exception) -> DatasetError:
    """The one-line error for an LMDB that cannot be read (py-lmdb's message starts with the folder)."""
    reason = str(err).removeprefix(f"{path.resolve()}: ") or type(err).__name__
    size = (path / "data.mdb").stat().st_size
    return DatasetError(f"cannot read the LMDB in {path}: {reason} (data.mdb of {size} bytes: corrupt or incomplete?)")


def _open_env(path: Path) -> Any:
    """The read-only LMDB environment of folder ``path`` for this process.

    Raises:
        DatasetError: ``data.mdb`` is not an LMDB file, or is shorter than the pages it says it has.
    """
    key = str(path.resolve())
    pid, env = _ENVS.get(key, (None, None))
    if pid != os.getpid():
        if env is not None:
            env.close()  # the parent's handle, inherited by fork: release this process's copy, then reopen
            del _ENVS[key]
        lmdb = import_lmdb()
        try:
            env = lmdb.open(key, readonly=True, lock=False, readahead=False, meminit=False)
            used = (env.info()["last_pgno"] + 1) * env.stat()["psize"]
        except lmdb.Error as err:
            raise _lmdb_error(path, err) from None
        size = (path / "data.mdb").stat().st_size
        if size < used:  # a read past the file's end would kill the process (SIGBUS), not raise
            env.close()
            raise DatasetError(f"cannot read the LMDB in {path}: data.mdb holds {size} of its {used} bytes (truncated)")
        _ENVS[key] = (os.getpid(), env)
    return env


def read_lsun_indices(path: str | Path) -> np.ndarray:
    """Second column of UNICORN's ``indices.txt`` as (N,) int64.

    The file is UTF-8 text of lines ``<j> <k>``, two integers separated by white space; blank lines and ``#``
    comments are ignored (as ``np.loadtxt`` did).

    Raises:
        DatasetError: the file is not such text, naming its first bad line, or lists no index.
    """
    text = read_text(path)
    kept = []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        try:
            _, k = (int(field) for field in fields)  # ValueError too when there are not two
        except ValueError:
            raise DatasetError(
                f"line {number} of {path}: expected two integers '<j> <k>', got {line.strip()!r}"
            ) from None
        kept.append(k)
    if not kept:
        raise DatasetError(f"{path} lists no indices (expected lines of two integers '<j> <k>')")
    return np.array(kept, dtype=np.int64)


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
        padding: fraction of the image size added on every side (0.1 in the reference), > -0.5 (negative: cut away).
        jitter: fraction of the image size by which boxes move when augmenting (0.1), in [0, 0.5).
        on_error: ``"raise"`` or ``"skip"`` undecodable or unreadable records.

    An LMDB that cannot be opened or listed, or a malformed ``indices.txt``, is a
    :class:`~unicorn.data.images.DatasetError` naming it, whatever ``on_error``.

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
        if not 0.0 <= jitter < 0.5:  # from 0.5 on, a box's opposite corners may cross
            raise DatasetError(f"jitter must be in [0, 0.5) (a fraction of the image size), got {jitter}")
        if not padding > -0.5:  # -0.5 takes half the image away on every side: nothing is left
            raise DatasetError(
                f"padding must be > -0.5 (a fraction of the image size added on every side), got {padding}"
            )
        lmdb = import_lmdb()  # fail early, with the install hint
        root = require(root, "LSUN root", _HINT)
        self.path = require(root / tag, f"LSUN '{tag}' LMDB folder", _HINT)
        require(self.path / "data.mdb", f"LSUN '{tag}' LMDB file", _HINT)
        self.tag, self.img_size, self.augment = tag, int(img_size), bool(augment)
        self.padding, self.jitter = float(padding), float(jitter)
        # keys are read once, in LMDB (byte-sorted) order, the order indices.txt refers to
        env = _open_env(self.path)
        try:
            with env.begin(write=False) as txn:
                keys = [bytes(k) for k in txn.cursor().iternext(keys=True, values=False)]
        except lmdb.Error as err:
            raise _lmdb_error(self.path, err) from None
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
        env, lmdb = _open_env(self.path), import_lmdb()
        try:
            with env.begin(write=False) as txn:
                data = txn.get(key)
        except lmdb.Error as err:  # a corrupt page: this record is lost, maybe not the others
            raise ImageLoadError(name, f"{type(err).__name__}: {err}") from None
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
