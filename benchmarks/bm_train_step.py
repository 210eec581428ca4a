"""Training-step benchmark: where the time of a pose step and of a 3D step goes.

For the small and big models (the reference's real-image settings, 64 px, stage 4 so that every code and the
neighbour loss are active, neighbour memory filled) it times one pose step and one 3D step at batch 32, split into

- the forward time of the encoders, the generators (shape, texture, background, pose and scale heads), the
  renderer, the perceptual loss and the mesh regularisers (forward hooks; the neighbour loss's renders and
  predictions count in their components), ``other`` = the rest of the forward (MSE, memory search, glue),
- the backward pass (all of it) and the optimizer step (Adam),

as medians over ``--repeats`` steps. The VGG16 of the perceptual loss gets random weights unless ``--vgg`` names
torchvision's file (the time is the same).

    python benchmarks/bm_train_step.py                  # CPU, small and big, batch 32
    python benchmarks/bm_train_step.py --device cuda
    python benchmarks/bm_train_step.py --models small --repeats 2 --batch 8
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import defaultdict

import torch

from unicorn.model import Unicorn, unicorn_config
from unicorn.model.perceptual import _CONVS, VGGPerceptualLoss

GROUPS = ("encoder", "generators", "renderer", "perceptual", "regularisers")
COLUMNS = ("forward", *GROUPS, "other", "backward", "optimizer", "total")


class ComponentTimer:
    """Accumulates the forward time of groups of modules through forward pre-hooks and hooks."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.totals: dict[str, float] = defaultdict(float)
        self._open: dict[int, float] = {}
        self._depth = 0

    def _sync(self) -> None:
        if self.device == "cuda":
            torch.cuda.synchronize()

    def attach(self, group: str, module: torch.nn.Module | None) -> None:
        if module is None:
            return

        def begin(mod: torch.nn.Module, inputs: object) -> None:
            self._sync()
            self._open[id(mod)] = time.perf_counter()

        def end(mod: torch.nn.Module, inputs: object, output: object) -> None:
            self._sync()
            self.totals[group] += time.perf_counter() - self._open.pop(id(mod))

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


def build(size: str, image_size: int, vgg: str | None, device: str) -> tuple[Unicorn, torch.optim.Optimizer]:
    cfg = unicorn_config("real", size, image_size=image_size, loss={"perceptual": None})
    model = Unicorn(cfg)
    # the perceptual term is computed whenever the module exists: give it real or random VGG16 weights
    model.perceptual = VGGPerceptualLoss(vgg if vgg else random_vgg_weights())
    model.to(device).train()
    stage4 = {"shape": cfg["shape"]["code_dim"], "texture": cfg["texture"]["code_dim"]}
    model.set_active_dims(**stage4, background=cfg["background"]["code_dim"])
    return model, torch.optim.Adam(model.parameters(), lr=1e-4)


def time_steps(model: Unicorn, opt: torch.optim.Optimizer, images: torch.Tensor, device: str, repeats: int) -> dict:
    timer = ComponentTimer(device)
    for encoder in model.encoders:
        timer.attach("encoder", encoder)
    for head in (model.shape, model.texture, model.background, model.pose, model.scale):
        timer.attach("generators", head)
    timer.attach("renderer", model.renderer)
    timer.attach("perceptual", model.perceptual)
    timer.attach("regularisers", model.normal_loss)
    timer.attach("regularisers", model.laplacian_loss)

    def sync() -> None:
        if device == "cuda":
            torch.cuda.synchronize()

    results = {}
    for phase, fn in (("pose", model.pose_step), ("3d", model.step_3d)):
        rows = []
        for i in range(repeats + 1):  # the first is a warm-up (and fills the neighbour memory)
            timer.reset()
            opt.zero_grad(set_to_none=True)
            sync()
            t0 = time.perf_counter()
            losses = fn(images)
            sync()
            t1 = time.perf_counter()
            losses["total"].backward()
            sync()
            t2 = time.perf_counter()
            opt.step()
            sync()
            t3 = time.perf_counter()
            if i == 0:
                continue
            row = {g: timer.totals.get(g, 0.0) for g in GROUPS}
            row.update(forward=t1 - t0, backward=t2 - t1, optimizer=t3 - t2, total=t3 - t0)
            row["other"] = row["forward"] - sum(row[g] for g in GROUPS)
            rows.append(row)
        results[phase] = {c: statistics.median(r[c] for r in rows) for c in COLUMNS}
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--models", nargs="+", default=["small", "big"], choices=["small", "big"])
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--vgg", default=None, help="torchvision's vgg16-397923af.pth (random weights otherwise)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    name = torch.cuda.get_device_name() if args.device == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    print(f"# UNICORN training step, batch {args.batch}, {args.image_size} px, stage 4, {name}; seconds (median)")
    print(f"{'model':6s} {'step':5s} " + " ".join(f"{c:>12s}" for c in COLUMNS))
    for size in args.models:
        model, opt = build(size, args.image_size, args.vgg, args.device)
        images = torch.rand(args.batch, 3, args.image_size, args.image_size, device=args.device)
        for phase, row in time_steps(model, opt, images, args.device, args.repeats).items():
            print(f"{size:6s} {phase:5s} " + " ".join(f"{row[c]:12.3f}" for c in COLUMNS), flush=True)


if __name__ == "__main__":
    main()
