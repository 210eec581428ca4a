"""Can the background generator draw the wild mode's backgrounds when the code is free?

The synthetic wild mode puts its objects in front of random backgrounds (solid, gradient, checker, smooth noise;
``unicorn.data.synthetic.render.random_background``). A trained model's backgrounds come out as one flat colour
per image. This probe separates the generator from the code regression: it fits a :class:`GiraffeGenerator` of the
given size together with one free code per background (no encoder) by Adam on the mean squared error, and prints
the error per background kind beside the error of one flat colour per image (the mean of each background, the best
a flat background can do). ``--active-dims`` masks the codes as a training stage does (the tiny model's background
code: 4, 8 and 16 entries in stages 1, 2 and 3-4).

    python experiments/background_fit.py --lr 2e-4 1e-3
    python experiments/background_fit.py --lr 2e-4 --active-dims 4
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import torch

from unicorn.data.synthetic.render import random_background
from unicorn.model.generator import GiraffeGenerator

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import non_negative_float, positive_float, positive_int, power_of_two, seed_number  # noqa: E402

KINDS = ("solid", "gradient", "checker", "noise")


def backgrounds(n: int, size: int, seed: int) -> tuple[torch.Tensor, list[str]]:
    """``n`` random backgrounds (n, 3, size, size) and their kinds (the kind is the generator's first draw)."""
    rng = np.random.default_rng(seed)
    images, kinds = [], []
    for _ in range(n):
        kinds.append(str(copy.deepcopy(rng).choice(KINDS)))
        images.append(random_background(rng, size))
    return torch.tensor(np.stack(images), dtype=torch.float32).permute(0, 3, 1, 2), kinds


def fit(
    target: torch.Tensor,
    code_dim: int,
    min_features: int,
    lr: float,
    steps: int,
    seed: int,
    code_std: float = 0.1,
    active_dims: int | None = None,
) -> torch.Tensor:
    """Per-image mean squared error (N,) after fitting the generator and a free code per image (initial codes
    ``code_std`` x a standard normal; only the first ``active_dims`` entries of each code reach the generator)."""
    torch.manual_seed(seed)
    gen = GiraffeGenerator(code_dim, target.shape[-1], min_features)
    codes = torch.nn.Parameter(code_std * torch.randn(target.shape[0], code_dim))
    mask = torch.zeros(code_dim)
    mask[: active_dims or code_dim] = 1
    opt = torch.optim.Adam([*gen.parameters(), codes], lr=lr)
    for _ in range(steps):
        loss = (gen(codes * mask) - target).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return (gen(codes * mask) - target).pow(2).mean((1, 2, 3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=positive_int, default=64, help="number of backgrounds")
    parser.add_argument("--size", type=power_of_two, default=32, help="image side (a power of 2)")
    parser.add_argument("--code-dim", type=positive_int, default=16, help="code size (the tiny model's: 16)")
    parser.add_argument("--min-features", type=positive_int, default=8, help="generator's smallest width (tiny: 8)")
    parser.add_argument(
        "--lr", type=positive_float, nargs="+", default=[2e-4, 1e-3], help="Adam learning rates to compare"
    )
    parser.add_argument("--steps", type=positive_int, default=1000, help="Adam steps of each fit")
    parser.add_argument(
        "--code-std", type=non_negative_float, default=0.1, help="initial codes' std (0: a regressor's zero start)"
    )
    parser.add_argument(
        "--active-dims",
        type=positive_int,
        default=None,
        help="code entries the generator sees, 1 to --code-dim (default: all; tiny: 4, 8, 16 by stage)",
    )
    parser.add_argument("--seed", type=seed_number, default=0)
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads")
    args = parser.parse_args()
    if args.active_dims is not None and args.active_dims > args.code_dim:
        parser.error(f"--active-dims must be at most --code-dim ({args.code_dim}), got {args.active_dims}")
    torch.set_num_threads(args.threads)

    target, kinds = backgrounds(args.n, args.size, args.seed)
    flat = (target - target.mean((2, 3), keepdim=True)).pow(2).mean((1, 2, 3))
    rows = [("one flat colour per image", flat)]
    sizes = (args.code_dim, args.min_features)
    for lr in args.lr:
        err = fit(target, *sizes, lr, args.steps, args.seed, args.code_std, args.active_dims)
        rows.append((f"generator + free codes, lr {lr:g}, {args.steps} steps", err))
    present = [k for k in KINDS if k in kinds]
    mask = {k: torch.tensor([c == k for c in kinds]) for k in present}
    print(
        f"{args.n} backgrounds at {args.size} px ({', '.join(f'{k} {int(mask[k].sum())}' for k in present)}); "
        f"code {args.code_dim} ({args.active_dims or args.code_dim} active), min features {args.min_features}; "
        "mean squared error"
    )
    print("| fit | all | " + " | ".join(present) + " |")
    print("|---|---|" + "---|" * len(present))
    for name, err in rows:
        cells = " | ".join(f"{err[mask[k]].mean().item():.4f}" for k in present)
        print(f"| {name} | {err.mean().item():.4f} | {cells} |")


if __name__ == "__main__":
    main()
