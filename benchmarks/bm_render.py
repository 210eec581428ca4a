"""Renderer benchmark: forward and forward+backward time and peak memory, beside a ResNet-18 training step.

Prints one row per (backend, batch, icosphere level, faces_per_pixel, image size), the median over several runs,
and each forward+backward time as a ratio to a ResNet-18 forward+backward on 32 images of 64 x 64, since the
renderer must not dominate a UNICORN training step. Every configuration runs in a fresh process so that its peak
memory is its own (CPU: peak RSS above the process's baseline after set-up; CUDA: peak allocated).

    python benchmarks/bm_render.py                 # CPU, the full table
    python benchmarks/bm_render.py --device cuda   # on a GPU
    python benchmarks/bm_render.py --quick         # fewer rows and runs
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import statistics
import time

import torch


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

    frags = renderer.rasterize(verts, faces, R, T)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated() / 2**20
    else:
        base = _rss_mib()
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="layered only at level 3, K = 25; 3 runs")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch sees no CUDA device")
    repeats = 3 if args.quick else args.repeats

    configs = []
    backends = ["layered"] if args.quick else ["layered", "softras"]
    for backend in backends:
        for level in [3] if args.quick else [3, 4]:
            for K in [25] if args.quick else [25, 50]:
                for batch in (32, 192):
                    configs.append((backend, batch, level, K, 64))
    configs.append(("layered", 32, 3, 25, 128))  # how time grows with pixels
    configs.append(("layered", 32, 3, 25, 256))

    ctx = mp.get_context("spawn")
    with ctx.Pool(1, maxtasksperchild=1) as pool:
        resnet = pool.apply(_resnet_step, (args.device, args.threads, repeats))
        rows = [pool.apply(_run_config, ((*c, args.device, args.threads, repeats),)) for c in configs]

    print(f"device={args.device} threads={args.threads} torch={torch.__version__} median of {repeats} runs, sigma=1e-4")
    print(f"ResNet-18 forward+backward, 32 x 3 x 64 x 64: {resnet:.3f} s")
    header = (
        f"{'backend':8} {'B':>4} {'lvl':>3} {'F':>5} {'K':>3} {'px':>4} {'fwd s':>7} {'fwd+bwd s':>9} "
        f"{'x ResNet':>8} {'peak MiB':>8} {'pairs':>8} {'slots':>5} {'overflow':>8}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['backend']:8} {r['batch']:>4} {r['level']:>3} {r['faces']:>5} {r['K']:>3} {r['size']:>4} "
            f"{r['fwd']:>7.3f} {r['fb']:>9.3f} {r['fb'] / resnet:>8.2f} {r['peak_mib']:>8.0f} {r['pairs']:>8} "
            f"{r['slots']:>5} {r['overflow']:>8}"
        )
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
