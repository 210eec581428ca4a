"""Renderer benchmark: forward and forward+backward time and peak memory, beside a ResNet-18 training step.

Prints one row per (backend, batch, icosphere level, faces_per_pixel, image size), the median over several runs,
and each forward+backward time as a ratio to a ResNet-18 forward+backward on 32 images of 64 x 64, since the
renderer must not dominate a UNICORN training step. Every configuration runs in a fresh process so that its peak
memory is its own (CPU: peak RSS above the process's baseline after set-up; CUDA: peak allocated).

    python benchmarks/bm_render.py                 # CPU, the full table
    python benchmarks/bm_render.py --device cuda   # on a GPU
    python benchmarks/bm_render.py --quick         # fewer rows and runs
    python benchmarks/bm_render.py --quick --ref main   # this tree beside a git revision, row by row

With ``--ref``, each configuration runs in this tree and in the revision one after the other (fresh processes,
the revision's ``unicorn`` first on the path; see ``revisions.py``), and the table gains their time ratios.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import git_revision, positive_int, require_cuda  # noqa: E402
from revisions import REPO, child_env, tree_of  # noqa: E402


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _median_time(fn, device: str, repeats: int) -> float:
    for _ in range(2):  # warm-up: allocator and page-fault costs of a fresh process settle after a couple of calls
        fn()
    times = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _run_config(args: tuple) -> dict:
    backend, batch, level, K, size, device, threads, repeats = args
    torch.set_num_threads(threads)
    from unicorn.geometry.mesh import ellipsoid, spherical_face_uvs
    from unicorn.geometry.rotations import look_at_view_transform
    from unicorn.render import TexturesUV, build_renderer

    v, f = ellipsoid(level, scale=0.6)
    R, T = look_at_view_transform(2.732, 30.0, torch.linspace(0, 360, batch + 1)[:-1])
    verts = v[None].repeat(batch, 1, 1).to(device)
    faces, R, T = f.to(device), R.to(device), T.to(device)
    uvs = spherical_face_uvs(v, f).to(device)
    maps = torch.rand(batch, 3, 64, 64, device=device)
    target = torch.rand(batch, 4, size, size, device=device)
    renderer = build_renderer(backend, image_size=size, sigma=1e-4, faces_per_pixel=K).to(device)

    def forward():
        with torch.no_grad():
            return renderer(verts, faces, TexturesUV(maps, uvs), R=R, T=T)

    def forward_backward():
        v_ = verts.clone().requires_grad_()
        m_ = maps.clone().requires_grad_()
        loss = ((renderer(v_, faces, TexturesUV(m_, uvs), R=R, T=T) - target) ** 2).mean()
        loss.backward()

    base = _rss_mib()  # CPU: the high-water mark before any render (ru_maxrss cannot be reset)
    frags = renderer.rasterize(verts, faces, R, T)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated() / 2**20
    fwd = _median_time(forward, device, repeats)
    fb = _median_time(forward_backward, device, repeats)
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else _rss_mib()) - base
    return {
        "backend": backend, "batch": batch, "level": level, "faces": f.shape[0], "K": K, "size": size,
        "fwd": fwd, "fb": fb, "peak_mib": peak, "pairs": frags.num_pairs, "slots": frags.num_slots,
        "overflow": frags.overflow,
    }  # fmt: skip


def _resnet_step(device: str, threads: int, repeats: int) -> float:
    torch.set_num_threads(threads)
    from unicorn.model.encoder import ResNet18

    net = ResNet18().to(device)
    x = torch.rand(32, 3, 64, 64, device=device)

    def step():
        net.zero_grad()
        net(x).square().mean().backward()

    return _median_time(step, device, repeats)


def _in_process(tree: Path, threads: int, call: str) -> object:
    """``call`` (an expression over this script's functions) evaluated in a fresh process importing ``tree``'s
    ``unicorn``: each configuration's peak memory is its own."""
    code = f"import json, bm_render; print(json.dumps(bm_render.{call}))"
    env = child_env(tree, threads)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"bm_render.py: error: {call} in {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _configs(quick: bool) -> list[tuple]:
    configs = []
    for backend in ["layered"] if quick else ["layered", "softras"]:
        for level in [3] if quick else [3, 4]:
            for K in [25] if quick else [25, 50]:
                for batch in (32, 192):
                    configs.append((backend, batch, level, K, 64))
    configs.append(("layered", 32, 3, 25, 128))  # how time grows with pixels
    configs.append(("layered", 32, 3, 25, 256))
    return configs


def _print_table(rows: list[dict], resnet: float, ref_rows: list[dict] | None) -> None:
    header = (
        f"{'backend':8} {'B':>4} {'lvl':>3} {'F':>5} {'K':>3} {'px':>4} {'fwd s':>7} {'fwd+bwd s':>9} "
        f"{'x ResNet':>8} {'peak MiB':>8} {'pairs':>8} {'slots':>5} {'overflow':>8}"
    )
    if ref_rows:
        header += f" {'ref fwd':>7} {'ref f+b':>7} {'ref MiB':>7} {'fwd/ref':>7} {'f+b/ref':>7}"
    print(header)
    print("-" * len(header))
    for i, r in enumerate(rows):
        line = (
            f"{r['backend']:8} {r['batch']:>4} {r['level']:>3} {r['faces']:>5} {r['K']:>3} {r['size']:>4} "
            f"{r['fwd']:>7.3f} {r['fb']:>9.3f} {r['fb'] / resnet:>8.2f} {r['peak_mib']:>8.0f} {r['pairs']:>8} "
            f"{r['slots']:>5} {r['overflow']:>8}"
        )
        if ref_rows:
            q = ref_rows[i]
            line += (
                f" {q['fwd']:>7.3f} {q['fb']:>7.3f} {q['peak_mib']:>7.0f} {r['fwd'] / q['fwd']:>7.2f} "
                f"{r['fb'] / q['fb']:>7.2f}"
            )
        print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads of every run")
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed runs per row (the median is printed)")
    parser.add_argument("--quick", action="store_true", help="layered only at level 3, K = 25; 3 runs")
    parser.add_argument(
        "--ref", type=git_revision, help="also run every configuration in this git revision (e.g. main), side by side"
    )
    args = parser.parse_args()
    require_cuda(parser, args.device)
    repeats = 3 if args.quick else args.repeats
    ref_tree = tree_of(args.ref) if args.ref else None

    resnet = _in_process(REPO, args.threads, f"_resnet_step({args.device!r}, {args.threads}, {repeats})")
    rows, ref_rows = [], []
    for c in _configs(args.quick):
        call = f"_run_config({(*c, args.device, args.threads, repeats)!r})"
        rows.append(_in_process(REPO, args.threads, call))
        if ref_tree is not None:
            ref_rows.append(_in_process(ref_tree, args.threads, call))

    print(f"device={args.device} threads={args.threads} torch={torch.__version__} median of {repeats} runs, sigma=1e-4")
    if ref_tree is not None:
        print(f"ref: {args.ref} (ref columns; ratios are this tree / ref, each pair of runs back to back)")
    print(f"ResNet-18 forward+backward, 32 x 3 x 64 x 64: {resnet:.3f} s")
    _print_table(rows, resnet, ref_rows or None)
    targets = [r for r in rows if (r["backend"], r["level"], r["K"], r["size"]) == ("layered", 3, 25, 64)]
    print("\ntargets (layered, level 3, K = 25, sigma = 1e-4, 64 px):")
    for r in targets:
        bound = 1.0 if r["batch"] == 32 else 5.0
        ok = r["fb"] / resnet <= bound and (r["batch"] == 32 or r["peak_mib"] < 2048)
        mem = "" if r["batch"] == 32 else f", peak {r['peak_mib']:.0f} MiB (< 2048)"
        print(
            f"  batch {r['batch']:>3}: {r['fb'] / resnet:.2f} x ResNet (<= {bound}){mem}: {'met' if ok else 'MISSED'}"
        )


if __name__ == "__main__":
    main()
