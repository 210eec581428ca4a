"""Time and peak memory of the ShapeNet metrics at the reference's sizes.

Usage::

    OMP_NUM_THREADS=2 python benchmarks/bm_metrics.py [--device cpu|cuda] [--points 100000] [--icp-iters 100]
    python benchmarks/bm_metrics.py --device cuda --backends auto,torch      # the k-d trees beside the brute force

Prints the wall time and the peak memory (CPU: peak resident set size increase, CUDA: peak allocated) of a
Chamfer-L1 + normal consistency evaluation between two clouds of ``--points`` points, and of the gradient ICP,
for each nearest-neighbour backend of ``--backends`` (see :mod:`unicorn.metrics.nn`) in turn.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import torch

from unicorn.geometry.mesh import icosphere
from unicorn.metrics import gradient_icp, point_cloud_scores, sample_points_from_meshes
from unicorn.metrics.nn import BACKENDS

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import names, positive_int, require_cuda  # noqa: E402


def _peak_rss_mib() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return usage / 1024 if sys.platform != "darwin" else usage / 2**20


def _run(name: str, fn, device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    rss0 = _peak_rss_mib()
    t0 = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - t0
    if device.type == "cuda":
        mem = f"peak CUDA alloc +{(torch.cuda.max_memory_allocated() - base) / 2**20:.0f} MiB"
    else:
        mem = f"peak RSS +{_peak_rss_mib() - rss0:.0f} MiB (process peak {_peak_rss_mib():.0f} MiB)"
    print(f"{name:<48s} {elapsed:8.2f} s   {mem}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", choices=("cpu", "cuda"))
    parser.add_argument("--points", type=positive_int, default=100_000, help="points per cloud")
    parser.add_argument("--icp-iters", type=positive_int, default=100, help="gradient ICP iterations")
    parser.add_argument("--skip-icp", action="store_true")
    parser.add_argument(
        "--backends",
        type=names(("auto", *BACKENDS)),
        default="auto",
        help="comma-separated, of auto, " + ", ".join(BACKENDS),
    )
    args = parser.parse_args(argv)
    require_cuda(parser, args.device)
    backends = args.backends
    device = torch.device(args.device)
    print(f"device={device} threads={torch.get_num_threads()} points={args.points} torch={torch.__version__}")

    verts, faces = icosphere(4)
    shape = verts * torch.tensor([0.5, 0.3, 0.2])
    gt, gt_n = sample_points_from_meshes(shape[None], faces, args.points, seed=0)
    deformed = shape * (1 + 0.1 * torch.sin(5 * shape))
    pred, pred_n = sample_points_from_meshes(deformed[None], faces, args.points, seed=1)
    gt, gt_n, pred, pred_n = (t.to(device) for t in (gt, gt_n, pred, pred_n))

    moved = pred * torch.tensor([1.1, 0.9, 1.0], device=device) + 0.05
    for backend in backends:

        def chamfer(backend: str = backend) -> None:
            s = point_cloud_scores(pred, gt, pred_n, gt_n, backend=backend)
            print(f"    chamfer-L1={s.chamfer_l1.item():.4f} normal-cos={s.normal_cos.item():.4f}")

        def icp(backend: str = backend) -> None:
            r = gradient_icp(moved, gt, pred_n, n_iter=args.icp_iters, backend=backend)
            print(f"    icp loss={r.loss.item():.3e} scale={[round(x, 3) for x in r.scale[0].tolist()]}")

        # untimed: load (or compile, on first use) the search kernels, which a process does once
        gradient_icp(moved[:, :1000], gt[:, :1000], n_iter=2, backend=backend)
        _run(f"[{backend}] chamfer-L1 + normal-cos {args.points} x {args.points}", chamfer, device)
        if not args.skip_icp:
            _run(f"[{backend}] gradient ICP {args.icp_iters} it, {args.points} pts", icp, device)


if __name__ == "__main__":
    main()
