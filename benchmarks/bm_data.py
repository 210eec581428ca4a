"""Images per second of the dataset loaders, per DataLoader worker count, beside what a GPU training step consumes.

Usage::

    python benchmarks/bm_data.py                                   # folder and CUB loaders, 0, 1, 2 workers, 64 px
    python benchmarks/bm_data.py --loaders cub_200 --workers 0,4 --batches 40
    python benchmarks/bm_data.py --root DIR                        # write (or reuse) the generated data in DIR

The data is generated in the loaders' real on-disk formats, into a temporary folder (or ``--root``):

- ``folder``: a folder of JPEG photos (:class:`unicorn.data.folder.ImageFolder`, also CompCars' loader);
- ``cub_200``: CUB-200-2011's layout, ``images/<class>/<file>.jpg`` and CMR's annotations
  ``cachedir/cub/data/{train,val,test}_cub_cleaned.mat`` with boxes, full-size masks and 15 keypoints (val and test
  hold the first five images) (:class:`unicorn.data.cub.CUB200`; Pascal3D+ shares its crop-and-resize path).

Every photo is a JPEG of ``--source-size`` pixels (CUB's photos are about 500 x 375), a smooth random colour field with
fine noise so that it decodes like a photo. For each loader and worker count the script iterates the training loader
as ``unicorn-train`` builds it (:class:`unicorn.lit.UnicornDataModule` with its endless seeded stream: decoding,
cropping, resizing, augmentation, collation into batches of ``--batch-size``) and prints, over ``--batches`` batches
after ``--warmup`` (the workers' start-up), images per second of wall time in total and per worker (with 0 workers:
the main process), and images per CPU second of the processes that load them (the workers, or the main process):
on a machine shared with other work, the per-worker rate a core of its own gives. Beside them:
the rate a GPU training step consumes, ``--step-images`` images per ``--step-seconds`` (32 per 0.02 s = 1600 images
per second by default), and the number of workers that rate needs at the measured per-worker rate (per CPU second
where it is known). With ``--repeats N`` each row is the best of N measurements, the one least slowed by other work.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.io
import torch
from PIL import Image

from unicorn.lit import UnicornDataModule

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import comma_list, names, non_negative_int, positive_float, positive_int  # noqa: E402

LOADERS = ("folder", "cub_200")
#: CUB's class folders used by the generated data (any names work)
_CUB_CLASSES = ("001.Black_footed_Albatross", "002.Laysan_Albatross", "003.Sooty_Albatross")
_CUB_KEYPOINTS = 15
_CUB_FIELDS = ("rel_path", "bbox", "parts", "mask")


def write_photo(path: Path, width: int, height: int, seed: int, quality: int = 90) -> None:
    """A JPEG photo stand-in: a smooth random colour field plus fine noise (entropy like a photo's)."""
    rng = np.random.default_rng(seed)
    grid = Image.fromarray(rng.integers(0, 256, size=(6, 8, 3), dtype=np.uint8))
    smooth = np.asarray(grid.resize((width, height), Image.Resampling.BICUBIC), dtype=np.float32)
    noisy = np.clip(smooth + rng.normal(0.0, 12.0, size=smooth.shape), 0, 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(noisy).save(path, quality=quality)


def _cub_record(rng: np.random.Generator, rel_path: str, width: int, height: int) -> dict:
    """One CMR-style annotation: a box, an elliptic mask inside it (full size, uint8) and keypoints (1-based)."""
    x1, y1 = int(rng.integers(0, width // 4)), int(rng.integers(0, height // 4))
    x2, y2 = int(rng.integers(3 * width // 4, width)), int(rng.integers(3 * height // 4, height))
    yy, xx = np.mgrid[0:height, 0:width]
    cx, cy, rx, ry = (x1 + x2) / 2, (y1 + y2) / 2, (x2 - x1) / 2, (y2 - y1) / 2
    mask = (((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1.0).astype(np.uint8)
    angles, radius = rng.uniform(0, 2 * np.pi, _CUB_KEYPOINTS), rng.uniform(0, 0.6, _CUB_KEYPOINTS)
    visible = (rng.random(_CUB_KEYPOINTS) < 0.8).astype(np.float64)
    parts = np.stack([np.round(cx + radius * rx * np.cos(angles)) + 1, np.round(cy + radius * ry * np.sin(angles)) + 1])
    parts = np.concatenate([parts * visible, visible[None]])  # (3, K): x, y, visible; invisible ones at 0
    bbox = {"x1": x1 + 1.0, "y1": y1 + 1.0, "x2": x2 + 1.0, "y2": y2 + 1.0}
    return {"rel_path": rel_path, "bbox": bbox, "parts": parts, "mask": mask}


def write_datasets(root: Path, n_images: int, source_size: tuple[int, int]) -> dict[str, Path]:
    """The two datasets under ``root`` (kept if already there with as many images); returns their roots."""
    width, height = source_size
    folder, cub = root / "folder", root / "cub_200"
    if len(list(folder.glob("*.jpg"))) != n_images:
        for i in range(n_images):
            write_photo(folder / f"photo_{i:05d}.jpg", width, height, seed=i)
    anno = cub / "cachedir" / "cub" / "data" / "train_cub_cleaned.mat"  # written last
    if not anno.exists() or len(list((cub / "images").rglob("*.jpg"))) != n_images:
        rng = np.random.default_rng(0)
        records = np.empty(n_images, dtype=[(name, "O") for name in _CUB_FIELDS])
        for i in range(n_images):
            rel = f"{_CUB_CLASSES[i % len(_CUB_CLASSES)]}/bird_{i:05d}.jpg"
            write_photo(cub / "images" / rel, width, height, seed=10_000 + i)
            record = _cub_record(rng, rel, width, height)
            for name in _CUB_FIELDS:
                records[i][name] = record[name]
        anno.parent.mkdir(parents=True, exist_ok=True)
        for split, part in (("val", records[:5]), ("test", records[:5]), ("train", records)):  # train.mat last
            scipy.io.savemat(anno.parent / f"{split}_cub_cleaned.mat", {"images": part}, do_compression=True)
    return {"folder": folder, "cub_200": cub}


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a process so far (Linux ``/proc``; None elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8").rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _loader_cpu(iterator: object) -> float | None:
    """CPU seconds so far of the processes that load the batches: the workers, or this process."""
    workers = getattr(iterator, "_workers", None) or []
    pids = [w.pid for w in workers] if workers else [os.getpid()]
    times = [_cpu_seconds(pid) for pid in pids]
    return None if any(t is None for t in times) else sum(times)  # type: ignore[misc]


def measure(name: str, root: Path, workers: int, args: argparse.Namespace) -> tuple[float, float | None]:
    """Images per second of wall time and per CPU second of the loading processes, over ``args.batches`` batches."""
    dm = UnicornDataModule(
        name, str(root), img_size=args.img_size, batch_size=args.batch_size, num_workers=workers, stream_seed=0
    )
    dm.setup("fit")
    iterator = iter(dm.train_dataloader())
    for _ in range(args.warmup):
        next(iterator)
    cpu0, t0 = _loader_cpu(iterator), time.perf_counter()
    for _ in range(args.batches):
        batch = next(iterator)
    wall = time.perf_counter() - t0
    cpu1 = _loader_cpu(iterator)
    assert batch["image"].shape == (args.batch_size, 3, args.img_size, args.img_size)
    del iterator
    images = args.batches * args.batch_size
    per_cpu = None if cpu0 is None or cpu1 is None or cpu1 <= cpu0 else images / (cpu1 - cpu0)
    return images / wall, per_cpu


def _size(text: str) -> tuple[int, int]:
    """An argparse ``type``: ``WIDTHxHEIGHT``, each side >= 4 (the generated boxes and masks need 4 pixels)."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() and int(p) >= 4 for p in parts):
        raise argparse.ArgumentTypeError(f"must be WIDTHxHEIGHT, whole numbers >= 4, got {text!r}")
    return int(parts[0]), int(parts[1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--loaders", type=names(LOADERS), default=LOADERS, help=f"comma-separated, of {', '.join(LOADERS)}"
    )
    parser.add_argument(
        "--workers",
        type=comma_list(non_negative_int),
        default=[0, 1, 2],
        help="comma-separated DataLoader worker counts",
    )
    parser.add_argument("--img-size", type=positive_int, default=64, help="side of the loaded images")
    parser.add_argument("--batch-size", type=positive_int, default=32)
    parser.add_argument("--batches", type=positive_int, default=12, help="timed batches per measurement")
    parser.add_argument(
        "--warmup", type=non_negative_int, default=2, help="batches before the timing (worker start-up)"
    )
    parser.add_argument("--repeats", type=positive_int, default=1, help="measurements per row; the best is printed")
    parser.add_argument("--images", type=positive_int, default=128, help="images per generated dataset")
    parser.add_argument("--source-size", type=_size, default=(500, 375), help="WIDTHxHEIGHT of the stored photos")
    parser.add_argument("--step-images", type=positive_int, default=32, help="images a GPU training step consumes")
    parser.add_argument("--step-seconds", type=positive_float, default=0.02, help="duration of that GPU step")
    parser.add_argument("--root", type=Path, default=None, help="where to write the data (default: a temp folder)")
    args = parser.parse_args(argv)
    loaders, worker_counts = args.loaders, args.workers
    need = args.step_images / args.step_seconds
    print(
        f"img_size={args.img_size} batch={args.batch_size} source={args.source_size[0]}x{args.source_size[1]} JPEG "
        f"cpus={os.cpu_count()} threads={torch.get_num_threads()} torch={torch.__version__}"
    )
    print(f"a GPU step consumes {args.step_images} images per {args.step_seconds} s = {need:.0f} images/s")
    with tempfile.TemporaryDirectory(prefix="bm_data_") as tmp:
        roots = write_datasets(args.root or Path(tmp), args.images, args.source_size)
        header = (
            f"{'loader':<10} {'workers':>7} {'images/s':>9} {'per worker':>10} {'per CPU s':>9} {'workers for GPU':>15}"
        )
        print(header)
        for name in loaders:
            for workers in worker_counts:
                runs = [measure(name, roots[name], workers, args) for _ in range(args.repeats)]
                rate = max(r for r, _ in runs)
                per_cpu = max((c for _, c in runs if c is not None), default=None)
                per_worker = rate / max(workers, 1)
                best = per_cpu if per_cpu is not None else per_worker
                cpu_text = f"{per_cpu:9.0f}" if per_cpu is not None else f"{'-':>9}"
                print(f"{name:<10} {workers:>7} {rate:9.0f} {per_worker:10.0f} {cpu_text} {math.ceil(need / best):>15}")


if __name__ == "__main__":
    main()
