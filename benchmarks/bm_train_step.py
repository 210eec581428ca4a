"""Training-step benchmark: where the time of a pose step and of a 3D step goes.

Models (stage 4, so every code and the neighbour loss are active; the neighbour memory is filled by warm-up
steps first):

- ``tiny``: the README main job's model exactly as ``experiment=synthetic`` composes it (32 px, batch 16,
  structural perceptual loss, ShapeNet family: no background);
- ``small`` / ``big``: the reference's real-image settings (64 px, batch 32, VGG16 perceptual loss);
- ``small-structural``: ``small`` with the weights-free structural loss instead of VGG16.

Each step is split into

- forward time of the encoders, the generators (shape, texture, background, pose and scale heads), the
  renderer, the perceptual loss, the mesh regularisers and the neighbour loss (all of its forward: memory
  search, re-encoding the neighbour images, their renders and losses; its inner modules count only there),
  ``other`` = the rest of the forward (MSE, glue);
- ``backward`` (all of it), and inside it ``bwd-nbr`` (the neighbour term's share: its graph is backpropagated
  first, with the rest of the graph kept, then the other terms) and ``bwd-render`` (the renderer's backward,
  measured by replaying the step's render calls on detached inputs with random output gradients);
- the optimizer step, the total, and the peak memory of the step (CUDA: ``max_memory_allocated``; CPU: the
  growth of the process's peak resident set over the step, 0 once the process has reached its plateau).

``kernels``: the aten ops one more step of each kind dispatches (forward, backward and optimizer; views and other
metadata-only ops left out). On CUDA each of them launches work from the host: the count bounds a step whose kernels
are small, as the main job's are on a GPU, and it is the same on every device. NaN for ``step:MODE`` rows (a
dispatch mode would break their graphs).

``pipelined``: seconds per step over ``--repeats`` more steps run back to back, no part timed, the device waited for
once at the end: on CUDA the host queues a step's kernels while the device runs the previous ones, as in training.
The other columns wait for the device between the parts they time (forward, backward, optimizer, each timed
module), so on CUDA their total adds the host's time and the device's where training overlaps them; on the CPU
``pipelined`` and ``total`` agree.

Medians over ``--repeats`` steps, after ``--warmup`` steps of each kind. The VGG16 of the perceptual loss gets
random weights unless ``--vgg`` names torchvision's file (the time is the same).

``--precision`` lists Lightning precisions to time side by side, one row per model, step and precision:
``32-true`` (the default) or ``bf16-mixed`` (the step's forward under ``torch.autocast`` in bfloat16, as Lightning's
``trainer.precision=bf16-mixed`` runs it; the renderer stays in float32). ``--compile`` does the same for
``model.compile`` (``none``: eager; a mode: the networks and the reconstruction loss compiled as ``unicorn-train``
compiles them (:func:`unicorn.model.compile.compile_modules`), during the warm-up steps; their encoder, generator and
perceptual times are part of ``other``, and with compiled rows every row runs its backward in one pass: the totals
are the figures to compare). ``step:MODE`` compiles each step's whole forward instead (``model.compile_scope=step``,
:class:`unicorn.lit.compiled.CompiledStep`, the steps without host reads; with ``step:reduce-overhead`` on CUDA,
CUDA graphs of whole steps, with ``step:cudagraphs`` the same of the eager kernels, without code generation): its
rows give the forward, backward, optimizer and total times only, and a comment line the time of each kind's first
compiled step (tracing and compiling included).

    python benchmarks/bm_train_step.py                               # CPU: tiny, small, small-structural, big
    python benchmarks/bm_train_step.py --models tiny --repeats 20
    python benchmarks/bm_train_step.py --device cuda --models small big
    python benchmarks/bm_train_step.py --device cuda --models small --precision 32-true bf16-mixed
    python benchmarks/bm_train_step.py --device cuda --models small --compile none default reduce-overhead
    python benchmarks/bm_train_step.py --device cuda --models small --paths sync-free --compile step:reduce-overhead
    python benchmarks/bm_train_step.py --device cuda --models small --paths sync-free --compile step:cudagraphs
    python benchmarks/bm_train_step.py --models tiny --paths default sync-free

``--paths`` lists the step paths to time side by side: ``default`` (the CPU's: exact sizes, reading the device back
where they depend on the data) and ``sync-free`` (the timed steps inside :func:`unicorn.hostsync.sync_free`, as
training runs them on CUDA: fixed rasterizer buffers sized by the warm-up steps, no host read).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import resource
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from unicorn.cli.allocator import tune_allocator
from unicorn.config import model_preset
from unicorn.hostsync import sync_free
from unicorn.lit.compiled import CompiledStep
from unicorn.model import Unicorn
from unicorn.model.compile import COMPILE_MODES, compile_modules, compile_unavailable
from unicorn.model.config import CODE_BRANCHES
from unicorn.objectives import Objectives, training_networks
from unicorn.objectives.perceptual import _CONVS, VGGPerceptualLoss
from unicorn.render import OverflowCounter

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling helper, however this script is loaded
from argchecks import existing_file, positive_int, require_cuda  # noqa: E402

GROUPS = ("encoder", "generators", "renderer", "perceptual", "regularisers", "neighbour")
COLUMNS = ("forward", *GROUPS, "other", "backward", "bwd-nbr", "bwd-render", "optimizer", "total", "peak MB")
MODELS = ("tiny", "small", "small-structural", "big")
#: Lightning precisions the benchmark times: their autocast dtype (None: no autocast)
PRECISIONS: dict[str, torch.dtype | None] = {"32-true": None, "bf16-mixed": torch.bfloat16}
#: ``--compile`` rows that compile each step's whole forward (model.compile_scope=step) in the mode that follows
STEP = "step:"


def autocast(device: str, precision: str) -> contextlib.AbstractContextManager[Any]:
    """The forward's context under Lightning's ``precision``: autocast to its dtype, or nothing."""
    dtype = PRECISIONS[precision]
    return contextlib.nullcontext() if dtype is None else torch.autocast(device_type=device, dtype=dtype)


class ComponentTimer:
    """Accumulates the forward time of groups of modules through forward pre-hooks and hooks.

    Nested timed modules count in the outermost group only (``override`` routes everything to one group while
    it is set, e.g. inside the neighbour loss).
    """

    def __init__(self, sync: Callable[[], None]) -> None:
        self.sync = sync
        #: False: the hooks neither wait for the device nor time (the pipelined steps)
        self.enabled = True
        self.totals: dict[str, float] = defaultdict(float)
        self._start: float | None = None
        self._depth = 0
        self.override: str | None = None

    @contextlib.contextmanager
    def region(self, group: str) -> Iterator[None]:
        """Time a block as ``group`` and route the modules called inside it to the same group."""
        if not self.enabled:
            yield
            return
        self.sync()
        t0 = time.perf_counter()
        self.override, previous = group, self.override
        try:
            yield
        finally:
            self.override = previous
            self.sync()
            self.totals[group] += time.perf_counter() - t0

    def attach(self, group: str, module: torch.nn.Module | None) -> None:
        if module is None:
            return

        def begin(mod: torch.nn.Module, inputs: object) -> None:
            if not self.enabled:
                return
            if self.override is None and self._depth == 0:
                self.sync()
                self._start = time.perf_counter()
            self._depth += 1

        def end(mod: torch.nn.Module, inputs: object, output: object) -> None:
            if not self.enabled:
                return
            self._depth -= 1
            if self.override is None and self._depth == 0:
                self.sync()
                self.totals[group] += time.perf_counter() - self._start

        module.register_forward_pre_hook(begin)
        module.register_forward_hook(end)

    def reset(self) -> None:
        self.totals.clear()


def random_vgg_weights() -> dict[str, torch.Tensor]:
    """A torchvision-named VGG16 state dict (up to relu3_3) with random values."""
    state = {}
    for index, cin, cout in _CONVS:
        state[f"features.{index}.weight"] = torch.randn(cout, cin, 3, 3) * (2.0 / (9 * cin)) ** 0.5
        state[f"features.{index}.bias"] = torch.zeros(cout)
    return state


def main_job_model_config() -> dict[str, Any]:
    """The model config of ``unicorn-train experiment=synthetic``, composed by Hydra like the CLI does."""
    from hydra import compose, initialize_config_dir

    from unicorn.config import model_config, validate
    from unicorn.resources import config_dir

    with initialize_config_dir(str(config_dir()), version_base=None):
        # an output folder is given so that no ${hydra:...} interpolation needs a running Hydra app
        cfg = compose("train", overrides=["experiment=synthetic", f"paths.output_dir={tempfile.gettempdir()}"])
    return model_config(validate(cfg))


def build(name: str, vgg: str | None, device: str) -> tuple[Unicorn, Objectives, torch.optim.Optimizer, int, int]:
    """Model, objectives, optimizer (as the trainer builds it), batch size and image size of one benchmarked
    setting."""
    if name == "tiny":
        cfg, batch = main_job_model_config(), 16
    else:
        size = "big" if name == "big" else "small"
        perceptual = "structural" if name == "small-structural" else None
        cfg, batch = model_preset("real", size, image_size=64, loss={"perceptual": perceptual}), 32
    model = Unicorn(cfg)
    objectives = Objectives.from_config(cfg["loss"], model)
    if name in ("small", "big"):
        # the perceptual term is computed whenever the module exists: give it real or random VGG16 weights
        objectives.steps["pose"].reconstruction.perceptual = VGGPerceptualLoss(vgg if vgg else random_vgg_weights())
    model.to(device).train()
    objectives.to(device)
    model.set_active_dims(**{name: cfg[name]["code_dim"] for name in CODE_BRANCHES if cfg[name] is not None})
    from unicorn.lit.module import UnicornLitModule

    opt = UnicornLitModule.make_optimizer(model.parameters(), {"lr": 1e-4})
    return model, objectives, opt, batch, cfg["image_size"]


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def sync_device(device: str) -> None:
    """Wait for the device's queued work (nothing to wait for on the CPU)."""
    if device == "cuda":
        torch.cuda.synchronize()


def timed_step(
    forward: Callable[[], Any], backward: Callable[[Any], float], opt: torch.optim.Optimizer, device: str
) -> dict[str, float]:
    """One step, its forward, backward and optimizer step each timed between device syncs: ``forward, backward,
    optimizer, total, peak MB``, and ``bwd-nbr``, what ``backward(losses)`` returns (the seconds of a first pass, or
    NaN)."""
    opt.zero_grad(set_to_none=True)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    rss0 = peak_rss_mb()
    sync_device(device)
    t0 = time.perf_counter()
    losses = forward()
    sync_device(device)
    t1 = time.perf_counter()
    first = backward(losses)
    sync_device(device)
    t2 = time.perf_counter()
    opt.step()
    sync_device(device)
    t3 = time.perf_counter()
    peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else peak_rss_mb() - rss0
    return {"forward": t1 - t0, "backward": t2 - t1, "bwd-nbr": first, "optimizer": t3 - t2, "total": t3 - t0,
            "peak MB": peak}  # fmt: skip


def pipelined(forward: Callable[[int], Any], opt: torch.optim.Optimizer, device: str, steps: int) -> float:
    """Seconds per step over ``steps`` steps run back to back, ``forward(k)`` the k-th one's losses, the device waited
    for once, at the end: on CUDA the host queues a step's kernels while the device runs the previous ones, as in
    training (the timed columns wait for the device between the parts of each step)."""
    sync_device(device)
    t0 = time.perf_counter()
    for k in range(steps):
        opt.zero_grad(set_to_none=True)
        forward(k)["total"].backward()
        opt.step()
    sync_device(device)
    return (time.perf_counter() - t0) / steps


class KernelCounter(TorchDispatchMode):
    """Counts the aten ops run inside it that are no view (:attr:`count`): the kernels they launch on CUDA."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        self.count += not func.is_view
        return func(*args, **(kwargs or {}))


def medians(rows: list[dict[str, float]]) -> dict[str, float]:
    """Each column's median over the timed steps; the peak memory's largest."""
    result = {c: statistics.median(r[c] for r in rows) for c in COLUMNS}
    result["peak MB"] = max(r["peak MB"] for r in rows)
    return result


def time_steps(
    model: Unicorn,
    objectives: Objectives,
    opt: torch.optim.Optimizer,
    images: torch.Tensor,
    device: str,
    args: argparse.Namespace,
    precision: str = "32-true",
    path: str = "default",
    compiled: bool = False,
    split: bool = True,
) -> dict:
    """Median timings of each step kind. ``compiled``: the networks and the reconstruction loss are compiled, so
    they are timed as part of ``other`` (a timing hook inside a compiled module would break its graph).
    ``split``: the neighbour term is backpropagated first, with the graph kept (``bwd-nbr``); without it, or
    compiled (a compiled backward runs once per graph), one backward (``bwd-nbr`` NaN)."""

    def sync() -> None:
        sync_device(device)

    timer = ComponentTimer(sync)
    if not compiled:
        for encoder in model.encoders:
            timer.attach("encoder", encoder)
        for head in (model.shape, model.texture, model.background, model.pose, model.scale):
            timer.attach("generators", head)
    timer.attach("renderer", model.renderer)
    shape_step = objectives.steps["3d"]
    if not compiled:
        timer.attach("perceptual", shape_step.reconstruction.perceptual)
    timer.attach("regularisers", shape_step.regularizer)

    # the neighbour loss: its whole forward is one group; remember its output to backpropagate it separately
    neighbors = shape_step.neighbors
    neighbour_loss = neighbors.forward

    def timed_neighbour_loss(*a: Any, **kw: Any) -> torch.Tensor:
        with timer.region("neighbour"):
            return neighbour_loss(*a, **kw)

    neighbors.forward = timed_neighbour_loss  # the 3D step calls the module, which calls this

    # the renderer's calls of the step, replayed afterwards to time its backward alone
    render_calls: list[tuple[tuple, dict]] = []

    def record(mod: torch.nn.Module, a: tuple, kw: dict) -> None:
        render_calls.append((a, kw))

    model.renderer.register_forward_pre_hook(record, with_kwargs=True)

    def replay_render_backward() -> float:
        def detach(x: Any) -> Any:
            if isinstance(x, torch.Tensor) and x.is_floating_point():
                return x.detach().requires_grad_(x.requires_grad)
            return x

        spent = 0.0
        calls = list(render_calls)
        render_calls.clear()  # the replays below pass through the same hook
        for a, kw in calls:
            a2 = tuple(detach(x) for x in a)
            kw2 = {k: detach(v) for k, v in kw.items()}
            textures = a2[2]
            if hasattr(textures, "maps"):
                textures = type(textures)(
                    detach(textures.maps),
                    textures.face_uvs,
                    wrap_u=textures.wrap_u,
                    align_corners=textures.align_corners,
                )
                a2 = (*a2[:2], textures, *a2[3:])
            with autocast(device, precision):  # the recorded textures may be bfloat16: cast as in the step
                out = model.renderer(*a2, **kw2)
            if not out.requires_grad:
                continue
            grad = torch.randn_like(out)
            sync()
            t0 = time.perf_counter()
            out.backward(grad)
            sync()
            spent += time.perf_counter() - t0
        return spent

    results = {}
    on_path = path == "sync-free"  # the steps after the warm-up, the pipelined ones and the counted one
    for phase in ("pose", "3d"):

        def fn(images: torch.Tensor, phase: str = phase, free: bool = False) -> Any:
            # the renders counted as training counts them (outside a counter an overflow would be read to warn)
            with autocast(device, precision), sync_free(free), OverflowCounter():
                return objectives(phase, model, images)

        def backward(losses: Any) -> float:
            nbr = losses.get("neighbor")
            if not split or compiled:
                losses["total"].backward()
                return float("nan")
            if nbr is None or not nbr.requires_grad:
                losses["total"].backward()
                return 0.0
            t0 = time.perf_counter()
            nbr.backward(retain_graph=True)
            sync()
            first = time.perf_counter() - t0
            (losses["total"] - nbr).backward()
            return first

        rows = []
        for i in range(args.warmup + args.repeats):
            timer.reset()
            render_calls.clear()
            free = on_path and i >= args.warmup  # the warm-up sizes the buffers
            row = timed_step(lambda free=free: fn(images, free=free), backward, opt, device)
            if i < args.warmup:
                continue
            row.update({g: timer.totals.get(g, 0.0) for g in GROUPS})
            if compiled:
                row.update(encoder=float("nan"), generators=float("nan"))
            row["other"] = row["forward"] - sum(row[g] for g in GROUPS if not math.isnan(row[g]))
            row["bwd-render"] = replay_render_backward()
            rows.append(row)
        results[phase] = medians(rows)
        timer.enabled = False
        results[phase]["pipelined"] = pipelined(lambda k: fn(images, free=on_path), opt, device, args.repeats)
        timer.enabled = True
        render_calls.clear()
        opt.zero_grad(set_to_none=True)
        with KernelCounter() as counter:
            fn(images, free=on_path)["total"].backward()
            opt.step()
        render_calls.clear()
        results[phase]["kernels"] = counter.count
    return results


def time_compiled_steps(
    model: Unicorn,
    objectives: Objectives,
    opt: torch.optim.Optimizer,
    images: torch.Tensor,
    device: str,
    args: argparse.Namespace,
    precision: str,
    mode: str,
) -> dict:
    """Median timings of each step kind with its whole forward compiled in ``mode`` (``model.compile_scope=step``):
    a checked eager step of each kind first (as a training's first two iterations: they size the rasterizer's
    buffers), then the compiled steps without host reads, compiled during the warm-up. Forward, backward, optimizer,
    total and peak memory; the component columns are NaN (a timing hook would break the graph)."""

    compiled = CompiledStep(objectives, model, mode)
    for phase in ("pose", "3d"):
        opt.zero_grad(set_to_none=True)
        with autocast(device, precision):
            objectives(phase, model, images)["total"].backward()
        opt.step()

    def backward(losses: Any) -> float:
        losses["total"].backward()
        return float("nan")

    results = {}
    for phase in ("pose", "3d"):

        def forward(phase: str = phase, iteration: int = 0) -> Any:
            with autocast(device, precision), sync_free(), OverflowCounter():
                return compiled(phase, images, False, iteration)

        rows = []
        for i in range(args.warmup + args.repeats):
            row = timed_step(lambda phase=phase, i=i: forward(phase, 2 + i), backward, opt, device)
            if i == 0:  # the first call traces, compiles (and where it captures, runs the warm-up of) the graphs
                print(f"# step:{mode} {phase}: the first compiled step took {row['total']:.1f} s", flush=True)
            if i >= args.warmup:
                rows.append({**dict.fromkeys(COLUMNS, float("nan")), **row})
        results[phase] = medians(rows)
        after = 2 + args.warmup + args.repeats  # the iterations go on
        more = lambda k, phase=phase, after=after: forward(phase, after + k)  # noqa: E731
        results[phase]["pipelined"] = pipelined(more, opt, device, args.repeats)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed steps of each kind")
    parser.add_argument(
        "--warmup", type=positive_int, default=3, help="untimed steps of each kind (fill the memory, size the buffers)"
    )
    parser.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument(
        "--vgg", type=existing_file, default=None, help="torchvision's vgg16-397923af.pth (random weights otherwise)"
    )
    parser.add_argument(
        "--precision", nargs="+", default=["32-true"], choices=list(PRECISIONS), help="rows per Lightning precision"
    )
    parser.add_argument(
        "--compile",
        nargs="+",
        default=["none"],
        choices=["none", *COMPILE_MODES, *(STEP + m for m in COMPILE_MODES)],
        help="rows per model.compile (step:MODE: model.compile_scope=step)",
    )
    parser.add_argument("--paths", nargs="+", default=["default"], choices=["default", "sync-free"])
    args = parser.parse_args()
    require_cuda(parser, args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    # what unicorn-train does at start (UNICORN_TUNE_MALLOC=0 measures glibc's defaults)
    tuned = tune_allocator()
    torch.manual_seed(0)
    if args.device == "cuda":
        torch.backends.cudnn.benchmark = True  # as unicorn-train trainer=gpu (the preset's benchmark: true)
    name = (
        torch.cuda.get_device_name() + ", cudnn autotuned"
        if args.device == "cuda"
        else f"CPU, {torch.get_num_threads()} threads"
    )
    name += ", malloc tuned" if tuned else ", malloc defaults"
    print(f"# UNICORN training step, stage 4, {name}, torch {torch.__version__}; seconds (median of {args.repeats})")
    head = f"{'model':17s} {'batch':>5s} {'px':>3s} {'precision':>10s} {'compile':>15s} {'path':>9s} {'step':4s} "
    print(head + " ".join(f"{c:>12s}" for c in (*COLUMNS, "pipelined", "kernels")))
    for size in args.models:
        for precision, mode, path in itertools.product(args.precision, args.compile, args.paths):
            # a fresh model per row group, from the same seed: every row times the same weights and memory
            torch.manual_seed(0)
            model, objectives, opt, batch, image_size = build(size, args.vgg, args.device)
            images = torch.rand(batch, 3, image_size, image_size, device=args.device)
            if mode.startswith(STEP):
                if path != "sync-free":
                    continue  # only the steps without host reads compile whole
                reason = compile_unavailable(args.device, mode.removeprefix(STEP))
                if reason is not None:
                    print(f"# {mode}: torch.compile cannot run on {args.device} ({reason})")
                    continue
                rows = time_compiled_steps(
                    model, objectives, opt, images, args.device, args, precision, mode.removeprefix(STEP)
                )
            else:
                compiled = [module for _, module in training_networks(model, objectives)]
                if mode != "none" and not compile_modules(compiled, mode, args.device):
                    continue  # the warning says why
                # with compiled rows beside, the eager rows' backward is one pass as well: the totals compare
                split = all(m == "none" for m in args.compile)
                rows = time_steps(
                    model, objectives, opt, images, args.device, args, precision, path, mode != "none", split
                )
            for phase, row in rows.items():
                cells = " ".join(f"{row[c]:12.1f}" if c == "peak MB" else f"{row[c]:12.4f}" for c in COLUMNS)
                cells += f" {row['pipelined']:12.4f} {row.get('kernels', float('nan')):12.0f}"
                label = f"{size:17s} {batch:5d} {image_size:3d} {precision:>10s} {mode:>15s} {path:>9s} {phase:4s}"
                print(f"{label} {cells}", flush=True)


if __name__ == "__main__":
    main()
