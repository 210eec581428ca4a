"""``unicorn-data``: generate the synthetic benchmark, or check that a dataset is laid out correctly.

Examples::

    unicorn-data synth --category chair --mode nmr --models 400 --out data/synth_chair --seed 0
    unicorn-data check cub_200 --root datasets/cub_200 --split test
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import torch

from unicorn import __version__
from unicorn.cli.errors import UsageError, add_debug_argument, folder_path, positive_int, report_errors, seed_number
from unicorn.cli.options import (
    HelpFormatter,
    add_image_limit_arguments,
    apply_common_arguments,
    check_categories_option,
    check_common_arguments,
    lsun_tag,
)
from unicorn.data.synthetic.shapes import CATEGORIES

__all__ = ["build_parser", "main"]


#: the option of ``unicorn-data synth`` that sets each generation setting (``synthetic.json``'s keys)
SYNTH_OPTIONS = {
    "mode": "--mode",
    "n_models": "--models",
    "seed": "--seed",
    "image_size": "--size",
    "n_views": "--views",
    "supersample": "--supersample",
    "n_points": "--points",
    "backgrounds": "--backgrounds",
    "background_kinds": "--background-kinds",
    "roll": "--roll",
    "shift": "--shift",
}


#: how ``unicorn-data synth``'s errors about a cache folder that cannot be used say to generate elsewhere
ANOTHER_FOLDER = "generate into another folder with --out DIR"


def _option_value(key: str, value: Any) -> str:
    """A recorded setting's value as ``unicorn-data synth`` takes it (``unset``: the option left out)."""
    if key == "backgrounds" and isinstance(value, bool):
        return "random" if value else "white"
    if value is None:
        return "unset"
    if isinstance(value, list):
        return ",".join(map(str, value))
    return str(value)


def _option_difference(key: str, recorded: Any, asked: Any) -> str:
    """A setting of a generated dataset that differs from the one asked for, named by its option
    (:data:`SYNTH_OPTIONS`): ``--size 64 (asked: 32)``; a setting of no option (the generator version) by its key."""
    option = SYNTH_OPTIONS.get(key)
    if option is None:
        return f"{key}={recorded!r} (asked: {asked!r})"
    return f"{option} {_option_value(key, recorded)} (asked: {_option_value(key, asked)})"


def _background_kinds(args: argparse.Namespace) -> list[str] | None:
    """``--background-kinds`` as a list (None: left out), refused as a usage error when it names no kind or an
    unknown one, or asks for random backgrounds where they are white."""
    from unicorn.data.synthetic.render import check_background_kinds

    if args.background_kinds is None:
        return None
    kinds = list(check_background_kinds(args.background_kinds.split(","), "--background-kinds"))
    if args.backgrounds == "white" or (args.backgrounds is None and args.mode == "nmr"):
        white = "--backgrounds white" if args.backgrounds == "white" else "--mode nmr draws white backgrounds"
        raise UsageError(
            f"--background-kinds {args.background_kinds} picks random backgrounds, but {white}: "
            "add --backgrounds random, or drop --background-kinds"
        )
    return kinds


def _synth(args: argparse.Namespace) -> int:
    from unicorn.data.synthetic.sampling import check_view_ranges
    from unicorn.data.synthetic.writer import (
        check_generation_counts,
        check_generation_sizes,
        check_manifest,
        check_output_folder,
        ensure_synthetic_dataset,
        generate_synthetic_dataset,
        generation_lock,
        generation_settings,
        synthetic_dataset_path,
    )
    from unicorn.io.staging import staged_folder

    # checked here, naming the options: the generator's own checks name its arguments
    check_generation_sizes(args.size, args.supersample, args.points, ("--size", "--supersample", "--points"))
    check_generation_counts(args.models, args.views, ("--models", "--views"))
    check_view_ranges(args.mode, args.roll, args.shift, ("--roll", "--shift"))
    categories = [c for arg in args.category for c in arg.split(",") if c]
    if not categories:
        raise UsageError(f"--category names no category; choose from {sorted(CATEGORIES)}")
    counts = f"{args.models} models x {len(categories)} categor{'y' if len(categories) == 1 else 'ies'}"
    start = time.perf_counter()
    options = {
        "image_size": args.size,
        "n_views": args.views,
        "supersample": args.supersample,
        "n_points": args.points,
        "backgrounds": {"random": True, "white": False}.get(args.backgrounds),
        "background_kinds": _background_kinds(args),
        "roll": args.roll,
        "shift": args.shift,
    }
    settings = generation_settings(categories, args.mode, args.models, args.seed, **options)
    if args.out is None:
        path = synthetic_dataset_path(categories, args.mode, args.models, args.seed)
        cached = (path / "synthetic.json").is_file()
        if cached:  # checked here too, naming the options that differ
            check_manifest(path, describe=_option_difference, elsewhere=ANOTHER_FOLDER, **settings)
        out = ensure_synthetic_dataset(
            None,
            categories,
            args.mode,
            args.models,
            args.seed,
            progress=not args.quiet,
            elsewhere=ANOTHER_FOLDER,
            **options,
        )
        if cached:  # checked against these settings by ensure_synthetic_dataset: nothing was generated
            print(f"{out} already holds {counts} with these settings")
            return 0
    else:
        out = Path(args.out).expanduser()
        # another process generating into --out (or training on it) waits until this one has moved its files
        with generation_lock(out):
            # refused here, naming --out, rather than in the folder the files are first written to
            check_output_folder(out, categories, settings, _option_difference)
            # a generation stopped part-way (Ctrl-C, a full disk) leaves --out as it was
            with staged_folder(out) as staging:
                for record in ("metadata.yaml", "synthetic.json"):  # the categories already there stay listed
                    if (out / record).is_file():
                        shutil.copy2(out / record, staging / record)
                generate_synthetic_dataset(
                    staging, categories, args.mode, args.models, args.seed, progress=not args.quiet, **options
                )
    print(f"wrote {counts} to {out} in {time.perf_counter() - start:.1f} s")
    return 0


#: the unreadable items ``unicorn-data check --all`` names (it counts the others)
CHECK_SHOWN = 20


def _dataset_and_tag(name: str, tag: str | None) -> tuple[str, str | None]:
    """The loader and LSUN tag a ``check`` names: ``lsun_horse`` and ``lsun_motorbike`` (the ``dataset=`` configs)
    are ``lsun`` with their tag; ``lsun`` takes it from ``--tag``.

    Raises:
        UsageError: ``lsun`` without ``--tag``, a ``--tag`` that contradicts the name's, or one for another dataset.
    """
    loader, _, suffix = name.partition("_")
    if loader == "lsun" and suffix:
        if tag is not None and tag != suffix:
            raise UsageError(f"{name} is lsun with --tag {suffix}, not {tag}: drop --tag, or check lsun --tag {tag}")
        return loader, suffix
    return name, lsun_tag(name, tag, hint=", or check lsun_horse / lsun_motorbike")


def _check(args: argparse.Namespace) -> int:
    from unicorn.data.registry import build_dataset

    name, tag = _dataset_and_tag(args.dataset, args.tag)
    check_categories_option(name, args.categories)
    categories = None
    if args.categories is not None:  # comma- or space-separated, as the other commands' --categories and --category
        categories = [c for arg in args.categories for c in arg.split(",") if c]
        if not categories:
            raise UsageError("--categories names no category; drop it to check every category")
    options = {"tag": tag} if name == "lsun" else {}
    dataset = build_dataset(name, args.split, args.root, categories=categories, **options)
    print(f"{args.dataset} {args.split}: {len(dataset)} items")
    if args.all:
        return _read_every_item(dataset)
    _print_layout(dataset[0])
    return 0


def _print_layout(item: dict[str, Any]) -> None:
    """Print an item's keys with their tensors' shapes and dtypes."""
    for key, value in item.items():
        desc = f"{tuple(value.shape)} {value.dtype}" if isinstance(value, torch.Tensor) else repr(value)
        print(f"  {key}: {desc}")


def _read_every_item(dataset: Any) -> int:
    """Read every item as training reads them; print the first readable one's layout, the unreadable ones (the
    first :data:`CHECK_SHOWN`) and how many there are. Returns 0 when all are readable, else 1."""
    from unicorn.data.images import ImageLoadError

    bad = []
    for index in range(len(dataset)):
        try:
            item = dataset[index]
        except ImageLoadError as err:  # an unreadable image, or annotations that do not fit it
            bad.append(f"item {index}: {err}")
            continue
        if len(bad) == index:  # the first readable item
            _print_layout(item)
    print(f"read every item: {len(dataset) - len(bad)} readable, {len(bad)} not")
    for line in bad[:CHECK_SHOWN]:
        print(f"  {line}")
    if len(bad) > CHECK_SHOWN:
        print(f"  ... and {len(bad) - CHECK_SHOWN} more")
    return 1 if bad else 0


class _Parser(argparse.ArgumentParser):
    """A subcommand's parser whose error for a missing ``check`` dataset says when ``--categories`` took it: the
    option takes every word after it (``check --categories chair synthetic --root D``)."""

    def parse_known_args(
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self.given = list(sys.argv[1:] if args is None else args)  # what error() looks at
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        missing = message.partition("the following arguments are required: ")[2].split(", ")
        given = getattr(self, "given", [])
        # --categories (or a prefix of it, which argparse takes too) followed by a word, not an option
        took = any(
            len(arg) > 2 and "--categories".startswith(arg) and not word.startswith("-")
            for arg, word in zip(given, given[1:])
        )
        if "dataset" in missing and took:
            message += " (--categories took every word after it: name the dataset before --categories)"
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``unicorn-data`` (subcommands ``synth`` and ``check``)."""
    parser = argparse.ArgumentParser(
        prog="unicorn-data",
        description="Generate the synthetic benchmark, or check that a dataset is laid out correctly.",
        epilog="examples: unicorn-data synth --category car --mode wild --models 100 --out data/synth_car; "
        "unicorn-data check cub_200 --root datasets/cub_200 --split test",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s (unicorn3d) {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    synth = sub.add_parser(
        "synth",
        help="generate the synthetic benchmark in the ShapeNet-NMR (DVR) layout",
        description="Generate the synthetic benchmark (procedural objects ray-cast with open3d, with their meshes, "
        "point clouds, masks and poses) in the ShapeNet-NMR (DVR) layout, into --out or the cache. A folder that "
        "already holds a category to generate is refused; other categories join it only with the same settings.",
        formatter_class=HelpFormatter,
    )
    synth.add_argument(
        "--category",
        action="append",
        default=None,
        help=f"category (repeat or comma-separate); one of {sorted(CATEGORIES)}; default chair",
    )
    synth.add_argument(
        "--mode",
        choices=["nmr", "wild"],
        default="nmr",
        help="nmr: views on a turntable, over white; wild: random viewpoints, distances and shifts, over random "
        "backgrounds",
    )
    synth.add_argument(
        "--backgrounds", choices=["random", "white"], default=None, help="default: the mode's (wild random, nmr white)"
    )
    synth.add_argument(
        "--background-kinds",
        default=None,
        help="random backgrounds of these kinds only, comma-separated: solid, gradient, checker, noise (default: all)",
    )
    synth.add_argument("--roll", type=float, default=None, help="wild mode: largest roll in degrees (default 15)")
    synth.add_argument(
        "--shift", type=float, default=None, help="wild mode: largest off-centre shift in view units (default 0.1)"
    )
    synth.add_argument(
        "--models", type=positive_int, default=200, help="models per category (70/10/20%% train/val/test)"
    )
    synth.add_argument(
        "--out",
        type=folder_path,
        default=None,
        help="output folder; default: one named after the settings in the cache, $UNICORN_CACHE/synthetic "
        "(~/.cache/unicorn/synthetic)",
    )
    synth.add_argument("--seed", type=seed_number, default=0, help="seed of the models and their views")
    synth.add_argument("--size", type=positive_int, default=64, help="image side in pixels")
    synth.add_argument("--views", type=positive_int, default=24, help="views per model")
    synth.add_argument("--supersample", type=positive_int, default=3, help="rays per pixel along each axis")
    synth.add_argument("--points", type=positive_int, default=20000, help="ground-truth surface points per model")
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(func=_synth)

    check = sub.add_parser(
        "check",
        help="load a dataset and print its size and the first item (--all: read every item, exit status 1 if any "
        "is unreadable)",
        description="Load a dataset's split as training reads it (its folders, split lists and "
        "annotation files checked), then print its item count and the first item's keys with their shapes and "
        "dtypes. --all reads every item too and lists the unreadable ones (exit status 1 if there are any).",
        formatter_class=HelpFormatter,
    )
    check.add_argument(
        "dataset",
        help="shapenet_nmr, synthetic, cub_200, p3d_car, compcars, lsun (lsun_horse, lsun_motorbike: lsun with that "
        "--tag) or folder",
    )
    check.add_argument(
        "--root",
        required=True,
        help="the dataset's folder (synthetic: the generated dataset's, with metadata.yaml; lsun: the folder above "
        "the tag's)",
    )
    check.add_argument("--split", choices=["train", "val", "test"], default="train", help="dataset split")
    check.add_argument(
        "--categories",
        nargs="*",
        default=None,
        help="ShapeNet / synthetic categories, comma- or space-separated (after the dataset: it takes every word "
        "that follows)",
    )
    check.add_argument(
        "--tag",
        default=None,
        help="lsun only: the LSUN category, e.g. horse (--root is the parent of its folder); lsun_horse and "
        "lsun_motorbike give theirs",
    )
    check.add_argument(
        "--all", action="store_true", help="read every item and list the unreadable ones (exit status 1 if any)"
    )
    add_image_limit_arguments(check)
    check.set_defaults(func=_check)

    for command in (synth, check):
        add_debug_argument(command)
        command.set_defaults(command_parser=command)  # its usage errors show the subcommand's usage
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``unicorn-data`` console script."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the subcommand's usage, where parse_args would show the top level's
        args.command_parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if getattr(args, "category", None) is None and args.command == "synth":
        args.category = ["chair"]
    if args.command == "check":
        check_common_arguments(args.command_parser, args)
        apply_common_arguments(args)
    return report_errors("unicorn-data", lambda: _run(args), args.debug)


def _run(args: argparse.Namespace) -> int:
    from unicorn.registry import load_plugins

    load_plugins()  # UNICORN_PLUGINS and the unicorn.plugins entry points: a plugin's dataset to check
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
