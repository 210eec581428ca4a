"""Tiny datasets in the exact on-disk formats of the real ones, written by code at test time; a PNG bomb."""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from PIL import Image

_RECORD_DTYPE = [
    ("id", "O"),
    ("rel_path", "O"),
    ("train", "O"),
    ("test", "O"),
    ("bbox", "O"),
    ("width", "O"),
    ("height", "O"),
    ("parts", "O"),
    ("mask", "O"),
    ("class_id", "O"),
    ("cad_index", "O"),
]


def make_record(rng: np.random.Generator, rel_path: str, width: int, height: int, n_kp: int, idx: int) -> dict:
    """One annotation: an ellipse-shaped object with keypoints inside it (1-based MATLAB coordinates)."""
    x1, y1 = int(rng.integers(0, width // 4)), int(rng.integers(0, height // 4))
    x2, y2 = int(rng.integers(3 * width // 4, width)), int(rng.integers(3 * height // 4, height))
    yy, xx = np.mgrid[0:height, 0:width]
    cx, cy, rx, ry = (x1 + x2) / 2, (y1 + y2) / 2, (x2 - x1) / 2, (y2 - y1) / 2
    mask = ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1.0
    # keypoints well inside the ellipse, some invisible
    angles = rng.uniform(0, 2 * np.pi, n_kp)
    radius = rng.uniform(0, 0.6, n_kp)
    kx, ky = cx + radius * rx * np.cos(angles), cy + radius * ry * np.sin(angles)
    vis = (rng.random(n_kp) < 0.8).astype(np.float64)
    parts = np.stack([np.round(kx) + 1, np.round(ky) + 1, vis])  # (3, K), 1-based
    parts[:2, vis == 0] = 0
    return {
        "id": idx,
        "rel_path": rel_path,
        "train": 1,
        "test": 0,
        "bbox": {"x1": x1 + 1.0, "y1": y1 + 1.0, "x2": x2 + 1.0, "y2": y2 + 1.0},
        "width": width,
        "height": height,
        "parts": parts,
        "mask": mask,
        "class_id": 1 + idx % 3,
        "cad_index": 1 + idx % 10,
    }


def write_struct_array(path: Path, records: list[dict], variable: str = "images") -> None:
    """Save records as a MATLAB struct array (dict fields become nested structs, bools become logical)."""
    arr = np.empty(len(records), dtype=_RECORD_DTYPE)
    for i, rec in enumerate(records):
        for key, _ in _RECORD_DTYPE:
            arr[i][key] = rec[key]
    path.parent.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(path, {variable: arr})


def write_photo(path: Path, width: int, height: int, seed: int) -> None:
    """A smooth random colour JPEG/PNG (format from the suffix)."""
    rng = np.random.default_rng(seed)
    grid = rng.integers(0, 256, size=(4, 4, 3), dtype=np.uint8)
    img = Image.fromarray(grid).resize((width, height), Image.Resampling.BILINEAR)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


def write_annotated_split(
    root: Path, image_subdir: str, anno: Path, rel_dirs: list[str], n: int, n_kp: int, seed: int
) -> list[dict]:
    rng = np.random.default_rng(seed)
    records = []
    for i in range(n):
        w, h = int(rng.integers(60, 120)), int(rng.integers(50, 110))
        rel = f"{rel_dirs[i % len(rel_dirs)]}/img_{seed}_{i:03d}.jpg"
        write_photo(root / image_subdir / rel, w, h, seed * 100 + i)
        records.append(make_record(rng, rel, w, h, n_kp, i))
    # one box touching the image border, to exercise edge padding
    records[0]["bbox"] = {
        "x1": 1.0,
        "y1": 1.0,
        "x2": float(records[0]["width"]),
        "y2": records[0]["bbox"]["y2"],
    }
    write_struct_array(anno, records)
    return records


# ---------------------------------------------------------------------------------------------- limits, bombs
def _png(header: bytes, data: bytes, *extra: tuple[bytes, bytes]) -> bytes:
    """A PNG file's bytes: the ``IHDR`` fields, then the ``extra`` chunks (kind, data), then ``data`` compressed."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    chunks = [chunk(b"IHDR", header), *(chunk(k, d) for k, d in extra), chunk(b"IDAT", zlib.compress(data))]
    return b"\x89PNG\r\n\x1a\n" + b"".join(chunks) + chunk(b"IEND", b"")


def bomb_png(path: Path, width: int = 20000, height: int = 20000, one_bit: bool = False) -> Path:
    """A valid PNG header announcing ``width x height`` RGB pixels (1-bit grayscale with ``one_bit``), a few
    hundred bytes on disk."""
    import struct

    depth, colour = (1, 0) if one_bit else (8, 2)
    header = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    row = b"\x00" + bytes(3 * min(width, 64))  # only the start of the image data: decoding would fail anyway
    path.write_bytes(_png(header, row))
    return path


def keyed_png16(path: Path, samples: np.ndarray, key: int | tuple[int, int, int]) -> Path:
    """A 16-bit grey ((H, W) ``samples``) or RGB ((H, W, 3)) PNG whose ``tRNS`` chunk makes the ``key`` grey level or
    colour transparent, written byte by byte (Pillow writes neither)."""
    import struct

    height, width = samples.shape[:2]
    colour = 0 if samples.ndim == 2 else 2
    rows = samples.astype(">u2").reshape(height, -1)
    data = b"".join(b"\x00" + row.tobytes() for row in rows)  # filter type 0 on every row
    header = struct.pack(">IIBBBBB", width, height, 16, colour, 0, 0, 0)
    transparent = struct.pack(">H", key) if colour == 0 else struct.pack(">HHH", *key)
    path.write_bytes(_png(header, data, (b"tRNS", transparent)))
    return path


def save_with_orientation(img: Image.Image, path: Path, orientation: int) -> Path:
    """Save an image (JPEG / PNG by suffix) with the EXIF orientation tag (6: stored turned 90 degrees
    counter-clockwise, shown turned clockwise, as a phone held upright stores it)."""
    exif = Image.Exif()
    exif[0x0112] = orientation
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path, exif=exif)
    return path


def swapped_rg_profile() -> bytes:
    """An ICC profile whose red and green primaries are sRGB's green and red (sRGB's otherwise): its colour (r, g, b)
    is sRGB's (g, r, b), so that a conversion to sRGB swaps two channels exactly."""
    from PIL import ImageCms

    icc = bytearray(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    count = int.from_bytes(icc[128:132], "big")  # the tag table: (signature, offset, size), 12 bytes a tag
    entries = {bytes(icc[132 + 12 * i : 136 + 12 * i]): 132 + 12 * i for i in range(count)}
    red, green = entries[b"rXYZ"], entries[b"gXYZ"]
    icc[red + 4 : red + 12], icc[green + 4 : green + 12] = icc[green + 4 : green + 12], icc[red + 4 : red + 12]
    icc[84:100] = bytes(16)  # no profile ID (an MD5 of the rest)
    # named apart from sRGB (the loaders read a profile named sRGB as stored), in as many UTF-16 characters
    return bytes(icc).replace("sRGB built-in".encode("utf-16-be"), "GRB swapped!!".encode("utf-16-be"))


def write_lsun(root: Path, tag: str, n: int) -> list[bytes]:
    """LSUN's layout of one category: ``root/<tag>`` an LMDB of ``n`` JPEGs (alternately 48 x 32 and 32 x 40) under
    hashed keys, and one record that is no image (``ffff_corrupt``); the images' keys, sorted. Skips the test
    without the optional ``lmdb`` package."""
    lmdb = pytest.importorskip("lmdb", reason="the optional 'lmdb' package is not installed")
    path = root / tag
    path.mkdir(parents=True)
    env = lmdb.open(str(path), map_size=1 << 26)
    keys = []
    with env.begin(write=True) as txn:
        for i in range(n):
            rng = np.random.default_rng(i)
            buf = io.BytesIO()
            w, h = (48, 32) if i % 2 else (32, 40)
            Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(buf, format="JPEG", quality=75)
            key = hashlib.sha1(str(i).encode()).hexdigest().encode()
            txn.put(key, buf.getvalue())
            keys.append(key)
        txn.put(b"ffff_corrupt", b"not a jpeg")
    env.close()
    return sorted(keys)
