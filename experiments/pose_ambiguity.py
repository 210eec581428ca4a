"""How much pose do the NMR views allow? A ceiling for ``rot-acc-30`` from the test objects' own renderings.

A mug seen with its handle behind the cup looks the same from a range of azimuths, and no model can tell its pose
from that image better than by a guess among them. This probe rebuilds the synthetic benchmark's test objects
(the generator is a deterministic function of the dataset's seed), renders each at the NMR views' elevation and
distance from ``360 / step`` azimuths (the generator's own ray caster, white background, the dataset's image size)
and, for each of the dataset's 24 views, finds the azimuths whose image differs from the view's by at most ``tau``
(mean squared error over the image). A pose estimator that sees only the image can do no better than choose among
those; choosing uniformly, it is within 30 degrees with the share of them that are. Averaged over the views, that
is the ceiling printed per ``tau`` beside the share of views with some image more than 30 degrees away within
``tau`` ("ambiguous"), and the median over views of the smallest error more than 30 degrees away.

``--vertical-light`` lights the objects from straight above, so that the shading says nothing about the azimuth and
only the shape and the colours do. About 15 seconds per category on a 2-core CPU.

    python experiments/pose_ambiguity.py --categories mug,car,chair,table,lamp
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from unicorn.data.synthetic.render import render_object
from unicorn.data.synthetic.sampling import NMR_FOV, model_streams, sample_views, split_indices, views_to_cameras
from unicorn.data.synthetic.shapes import CATEGORIES, build_object

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the scripts' shared argument checks
from argchecks import (  # noqa: E402
    at_least,
    comma_list,
    names,
    non_negative_float,
    positive_float,
    positive_int,
    seed_number,
)


def renders(
    category: str, index: int, seed: int, cameras: tuple, size: int, key_light: np.ndarray | None = None
) -> np.ndarray:
    """(A, size, size, 3) renderings of one object from the cameras ``(R (A, 3, 3), T (A, 3))`` of
    :func:`views_to_cameras` (the dataset's lighting, or ``key_light``)."""
    obj = build_object(category, model_streams(seed, category, index)[0])
    images, _ = render_object(obj, *cameras, image_size=size, fov=NMR_FOV, key_light=key_light)
    return images


def angular_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Absolute difference of azimuths in degrees, in [0, 180]."""
    d = np.abs(a - b) % 360.0
    return np.minimum(d, 360.0 - d)


def ceiling(images: np.ndarray, azims: np.ndarray, view_every: int, taus: list[float]) -> dict[str, np.ndarray]:
    """Per-view ceilings (V,) for each tau, the ambiguity flags and the smallest error beyond 30 degrees."""
    flat = images.reshape(len(images), -1)
    views = np.arange(0, len(images), view_every)
    mse = ((flat[views, None, :] - flat[None, :, :]) ** 2).mean(-1)  # (V, A)
    near = angular_distance(azims[views, None], azims[None, :]) <= 30.0
    out = {"min_far": np.where(near, np.inf, mse).min(1)}
    for tau in taus:
        alike = mse <= tau
        out[f"ceiling {tau:g}"] = (alike & near).sum(1) / alike.sum(1)
        out[f"ambiguous {tau:g}"] = (alike & ~near).any(1).astype(float)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--categories",
        type=names(CATEGORIES),
        default=["mug", "car", "chair", "table", "lamp"],
        help=f"comma-separated, of {', '.join(CATEGORIES)}",
    )
    parser.add_argument("--n-models", type=at_least(3), default=100, help="the dataset's models per category")
    parser.add_argument("--seed", type=seed_number, default=0, help="the dataset's seed")
    parser.add_argument("--size", type=positive_int, default=32, help="image side")
    parser.add_argument(
        "--step", type=positive_float, default=5.0, help="azimuth step of the renderings in degrees (divides 15)"
    )
    parser.add_argument(
        "--vertical-light",
        action="store_true",
        help="light from above instead of the dataset's key light: shading then says nothing about the azimuth",
    )
    parser.add_argument(
        "--taus",
        type=comma_list(non_negative_float),
        default=[0.0005, 0.001, 0.002, 0.005],
        help="comma-separated mean squared errors called alike",
    )
    args = parser.parse_args()
    taus = args.taus
    view_every = int(round(15.0 / args.step))  # the dataset's 24 views are every 15 degrees
    if view_every < 1 or abs(view_every * args.step - 15.0) > 1e-9:
        parser.error(f"--step must divide 15, got {args.step:g}")
    views = sample_views("nmr", int(round(360.0 / args.step)), np.random.default_rng())  # every step degrees
    azims, cameras = views["azim"], views_to_cameras(views)
    light = np.array([0.0, 1.0, 0.0]) if args.vertical_light else None

    columns = [f"ceiling {t:g}" for t in taus] + [f"ambiguous {t:g}" for t in taus]
    print(
        f"test objects of the synthetic benchmark (seed {args.seed}, {args.n_models} models per category), "
        f"{args.size} px, NMR views; renderings every {args.step:g} degrees of azimuth"
    )
    print(
        "| category | objects | "
        + " | ".join(f"rot-acc-30 ceiling, tau {t:g}" for t in taus)
        + " | "
        + " | ".join(f"ambiguous, tau {t:g}" for t in taus)
        + " | smallest error beyond 30 deg, median |"
    )
    print("|---|---|" + "---|" * (2 * len(taus) + 1))
    for category in args.categories:
        per_view: dict[str, list[np.ndarray]] = {}
        objects = sorted(split_indices(args.seed, category, args.n_models)["test"])
        for index in objects:
            images = renders(category, int(index), args.seed, cameras, args.size, light)
            res = ceiling(images, azims, view_every, taus)
            for k, v in res.items():
                per_view.setdefault(k, []).append(v)
        cells = [f"{np.concatenate(per_view[c]).mean():.3f}" for c in columns]
        median = float(np.median(np.concatenate(per_view["min_far"])))
        print(f"| {category} | {len(objects)} | " + " | ".join(cells) + f" | {median:.4f} |", flush=True)


if __name__ == "__main__":
    main()
