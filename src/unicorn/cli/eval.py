"""``unicorn-eval``: evaluate a checkpoint on a dataset; print the metric table, save it and a visual report.

Examples::

    unicorn-eval outputs/shapenet/runs/<time>/checkpoints/last.ckpt          # dataset of the training run
    unicorn-eval model.pkl --dataset cub_200 --root datasets/cub_200 --device cuda
    unicorn-eval last.ckpt --dataset synthetic --root ~/.cache/unicorn/synthetic/nmr_chair_n200_s0_v2 \\
        --max-images 64 --fast --out eval/chair

Writes ``metrics.csv``, ``metrics.json``, ``per_image.csv``, ``report.html`` and ``report.png`` to ``--out``
(default ``<run>/eval/<dataset>_<split>`` for a checkpoint inside a training run, else
``eval/<checkpoint>_<dataset>_<split>``); a folder that is not empty is refused unless ``--overwrite`` is given.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from unicorn import __version__
from unicorn.cli.allocator import tune_allocator
from unicorn.cli.errors import UsageError, folder_path, report_errors, seed_number, whole_number
from unicorn.cli.options import (
    HelpFormatter,
    add_common_arguments,
    add_overwrite_argument,
    apply_common_arguments,
    check_categories_option,
    check_common_arguments,
    check_out_folder,
    check_picture_sizes,
    check_ranged_options,
    lsun_tag,
    parse_device,
)
from unicorn.config.schema import FAST_EVAL, REPORT_TURNTABLE_FRAMES, SPLITS, EvaluateConfig
from unicorn.data.images import DatasetNotFoundError
from unicorn.data.registry import DATASET_NAMES, DATASETS, prepare_dataset
from unicorn.evaluation.protocols import EvalOptions
from unicorn.model.config import TemplateConfig
from unicorn.registry import PLUGINS_ENV

__all__ = ["build_parser", "main"]

log = logging.getLogger("unicorn.eval")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="unicorn-eval",
        description="Evaluate a UNICORN checkpoint (unicorn-train .ckpt, released .pkl or unicorn.io.save_model file) "
        "on a dataset with UNICORN's protocol for it; print the metrics and write them (CSV, JSON) with a visual "
        "report (HTML, PNG).",
        formatter_class=HelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s (unicorn3d) {__version__}")
    p.add_argument("checkpoint", help="checkpoint file")
    p.add_argument(
        "--dataset",
        help=f"dataset name ({', '.join(DATASET_NAMES)}, or a plugin's); default: the training run's dataset (from "
        "<run>/config.yaml)",
    )
    p.add_argument(
        "--root",
        help="dataset root (for synthetic: the generated dataset folder with metadata.yaml); default: the training "
        "run's, for its dataset",
    )
    p.add_argument("--split", default="test", choices=SPLITS, help="dataset split")
    p.add_argument(
        "--categories",
        help="ShapeNet / synthetic categories, comma-separated; default: the training run's, for its dataset, else all",
    )
    p.add_argument(
        "--tag",
        help="LSUN: the category whose folder is under --root (horse, motorbike); default: the training run's",
    )
    p.add_argument(
        "--skip-bad",
        action="store_true",
        help="skip unreadable images with a warning (the others are scored) instead of stopping",
    )
    p.add_argument(
        "--out",
        type=folder_path,
        help="output folder; default: <run>/eval/<dataset>_<split> for a checkpoint in a training run's "
        "checkpoints/ folder, else eval/<checkpoint name>_<dataset>_<split>",
    )
    p.add_argument("--device", default="auto", help="'auto' (CUDA when available), 'cpu', 'cuda' or 'cuda:N'")
    add_overwrite_argument(p, "once the evaluation is complete")
    _add_metric_arguments(p)
    _add_report_arguments(p)
    add_common_arguments(p)
    return p


def _add_metric_arguments(p: argparse.ArgumentParser) -> None:
    """What is scored and how finely (defaults: :class:`~unicorn.evaluation.EvalOptions`, the paper's protocol)."""
    p.add_argument("--max-images", type=whole_number, help="evaluate at most N images, spread over the split")
    p.add_argument("--batch-size", type=whole_number, default=EvalOptions.batch_size, help="images per forward pass")
    # default None: an option given wins over --fast's value (_mesh_settings)
    p.add_argument(
        "--num-points",
        type=whole_number,
        default=None,
        help=f"points sampled per mesh for Chamfer (default {EvalOptions.num_points}; with --fast "
        f"{FAST_EVAL['num_points']})",
    )
    p.add_argument(
        "--icp-iterations",
        type=whole_number,
        default=None,
        help=f"ICP iterations, 0: no -ICP metrics (default {EvalOptions.icp_iterations}; with --fast "
        f"{FAST_EVAL['icp_iterations']})",
    )
    p.add_argument(
        "--fast",
        action="store_true",
        help=f"UNICORN's validation setting: {FAST_EVAL['num_points'] // 1000}k points and "
        f"{FAST_EVAL['icp_iterations']} ICP iterations, where --num-points and --icp-iterations are not given",
    )
    p.add_argument(
        "--num-pairs", type=whole_number, default=EvalOptions.num_pairs, help="keypoint-transfer pairs (CUB)"
    )
    p.add_argument(
        "--mean-shape",
        type=whole_number,
        default=0,
        metavar="ITERATIONS",
        help="ShapeNet / synthetic: fit each category's mean shape to its training objects with this many "
        "iterations (e.g. 300) and score it beside the model on the category's objects (chamfer-L1-ICP-mean-shape, "
        "shape-win; not with --icp-iterations 0); 0: off",
    )
    p.add_argument(
        "--own-mean-shape",
        action="store_true",
        help="ShapeNet / synthetic / Pascal3D+: also score the model's own average shape over the evaluated images "
        "with each image's predicted pose (chamfer-L1-ICP-own-mean, shape-win-own): do the per-image shapes "
        "follow the objects?",
    )
    p.add_argument(
        "--shape-points",
        type=whole_number,
        default=EvalOptions.shape_points,
        help="ShapeNet / synthetic: points per shape of the shape retrieval (shape-top1, shape-top3, shape-mrr, their "
        "-gt ceiling and -floor, shape-spread-ratio): is each reconstruction closest to its own object among the "
        "evaluated ones? 0: off",
    )
    p.add_argument("--no-align-pose", action="store_true", help="pose errors without canonical-frame alignment")
    p.add_argument(
        "--template-level",
        type=whole_number,
        help="icosphere level of the mesh (3: 642 vertices, 4: 2562); default: the model's, or the protocol's (CUB's "
        "keypoints: 4, as UNICORN's evaluation)",
    )
    p.add_argument(
        "--average-texture",
        choices=("auto", "on", "off"),
        default="auto",
        help="mean-colour textures; auto: as the checkpoint was being trained",
    )


def _add_report_arguments(p: argparse.ArgumentParser) -> None:
    """The visual report and how the evaluation runs."""
    p.add_argument(
        "--report-samples",
        type=whole_number,
        default=EvalOptions.report_samples,
        help="images shown in the report (0: no report)",
    )
    p.add_argument("--view-size", type=whole_number, default=128, help="side of the report pictures")
    p.add_argument(
        "--turntable-frames",
        type=whole_number,
        default=REPORT_TURNTABLE_FRAMES,
        help="frames of the report's turntables (0: none)",
    )
    p.add_argument("--workers", type=whole_number, default=EvalOptions.num_workers, help="DataLoader workers")
    p.add_argument(
        "--nn-workers",
        type=whole_number,
        default=None,
        help="threads of scipy's nearest-neighbour search, used where pykdtree is not installed (-1: all cores; "
        "default: torch's thread count); pykdtree searches with OMP_NUM_THREADS threads",
    )
    p.add_argument(
        "--seed", type=seed_number, default=EvalOptions.seed, help="seed of the view choice and point sampling"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


#: option -> the settings field that declares its range (:func:`unicorn.model.ranges.ranged`)
_RANGED = {
    "batch_size": (EvalOptions, "batch_size"),
    "num_points": (EvalOptions, "num_points"),
    "num_pairs": (EvalOptions, "num_pairs"),
    "icp_iterations": (EvalOptions, "icp_iterations"),
    "report_samples": (EvalOptions, "report_samples"),
    "shape_points": (EvalOptions, "shape_points"),
    "workers": (EvalOptions, "num_workers"),
    "max_images": (EvaluateConfig, "max_images"),
    "turntable_frames": (EvaluateConfig, "turntable_frames"),
    "mean_shape": (EvaluateConfig, "mean_shape_iterations"),
    "template_level": (TemplateConfig, "level"),
}


def check_ranges(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse a value outside the range its evaluation setting declares (a usage error naming the option)."""
    check_ranged_options(parser, args, _RANGED)
    if args.view_size < 1:
        parser.error("--view-size must be >= 1")
    if args.nn_workers is not None and not (args.nn_workers == -1 or args.nn_workers >= 1):
        parser.error("--nn-workers must be -1 (all cores) or >= 1")


def _out_dir(args: argparse.Namespace, run_dir: Path | None, dataset: str | None) -> Path | None:
    """``--out``, or the default for the checkpoint's run folder and the dataset (None while the dataset is
    unknown)."""
    if args.out is not None:
        return args.out.expanduser()
    if dataset is None:
        return None
    if run_dir is not None:
        return run_dir / "eval" / f"{dataset}_{args.split}"
    return Path("eval") / f"{Path(args.checkpoint).stem}_{dataset}_{args.split}"


def _run_root(run_data: dict[str, Any]) -> str | None:
    """The dataset folder of a training run's ``dataset`` config (runs on generated data name the parent folder,
    where the data is generated again, as training does, if it was deleted since)."""
    name = run_data.get("name")
    if name not in DATASETS or not DATASETS.get(name).generated:
        return run_data.get("root")
    try:
        return str(prepare_dataset(name, run_data.get("root"), run_data.get("categories"), run_data.get("synthetic")))
    except DatasetNotFoundError as err:  # a root outside the cache that is gone; its hint is unicorn-train's override
        raise DatasetNotFoundError(
            err.path,
            "the training run's dataset.root",
            "Create the folder and unicorn-eval generates the run's data in it again, or give the generated "
            "dataset's folder with --root",
        ) from None


def _protocol_level(name: str | None) -> int | None:
    """The template level dataset ``name``'s protocol scores (:attr:`Protocol.template_level`), or None."""
    from unicorn.evaluation import get_protocol

    if name not in DATASETS:
        return None  # an unknown name is refused with the target
    level = get_protocol(DATASETS.get(name).protocol).template_level
    if level is not None:
        log.info("scoring the level-%d mesh, as the %s protocol does (--template-level to choose)", level, name)
    return level


def _target(args: argparse.Namespace, info: Any) -> Any:
    """The dataset split to evaluate: the options, completed from the checkpoint's training run.

    Raises:
        UsageError: no dataset or root given and none in the training run.
    """
    from unicorn.evaluation.session import EvalTarget

    run_data = info.dataset or {}
    dataset = args.dataset or run_data.get("name")
    if dataset is None:
        raise UsageError("no --dataset given and the checkpoint's training run does not name one")
    if dataset not in DATASETS:  # --dataset was checked: the training run's, registered by a plugin there
        raise UsageError(
            f"the checkpoint's training run read dataset {dataset!r}, which is not registered here (known: "
            f"{DATASETS.names()}): a dataset registered by a plugin needs that plugin here too ({PLUGINS_ENV}=module), "
            "or give --dataset and --root"
        )
    root = args.root
    if root is None and run_data.get("name") == dataset:
        root = _run_root(run_data)
    if root is None:
        raise UsageError(f"no --root given for dataset {dataset!r}")
    check_categories_option(dataset, args.categories)
    categories = _categories(args.categories)
    if categories is None and run_data.get("name") == dataset and run_data.get("categories"):
        categories = run_data["categories"]
    on_error = "skip" if args.skip_bad else "raise"
    # what the run read (LSUN's category...): build_eval_dataset keeps the options that say it
    options = dict(run_data.get("options") or {}) if run_data.get("name") == dataset else {}
    tag = lsun_tag(dataset, args.tag, options.get("tag"))
    if tag is not None:
        options["tag"] = tag
    return EvalTarget(dataset, str(root), args.split, categories, args.max_images, on_error, options)


def _categories(text: str | None) -> list[str] | None:
    """The names ``--categories`` gives, comma-separated, spaces around them left out (None: not given).

    Raises:
        UsageError: given but naming none (``--categories "$CATS"`` with the variable unset).
    """
    if text is None:
        return None
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise UsageError(f"--categories {text!r} names no category; give one, or drop --categories")
    return names


def _mesh_settings(args: argparse.Namespace) -> dict[str, int]:
    """``--num-points`` and ``--icp-iterations``: as given, else ``--fast``'s
    (:data:`~unicorn.config.schema.FAST_EVAL`), else the full protocol's (:class:`EvalOptions`)."""
    defaults = (
        FAST_EVAL if args.fast else {"num_points": EvalOptions.num_points, "icp_iterations": EvalOptions.icp_iterations}
    )
    return {key: defaults[key] if getattr(args, key) is None else getattr(args, key) for key in defaults}


def _options(args: argparse.Namespace, dataset: str, average_texture: bool) -> EvalOptions:
    """The evaluation options of the command line (:func:`_mesh_settings`: an option given wins over ``--fast``)."""
    from unicorn.evaluation import protocol_for

    return EvalOptions(
        protocol=protocol_for(dataset),
        batch_size=args.batch_size,
        **_mesh_settings(args),
        num_pairs=args.num_pairs,
        align_pose=not args.no_align_pose,
        average_texture=average_texture,
        report_samples=args.report_samples,
        num_workers=args.workers,
        nn_workers=args.nn_workers,
        seed=args.seed,
        progress=not args.quiet,
        own_mean_shape=args.own_mean_shape,
        shape_points=args.shape_points,
    )


def run(args: argparse.Namespace, command: str | None = None, produced_by: str | None = None) -> int:
    """Evaluate as ``args`` say (:func:`unicorn.evaluation.session.evaluate_to_folder` on the loaded checkpoint);
    returns the exit status.

    Args:
        args: parsed arguments.
        command: the ``unicorn-eval`` command line recorded as the results' provenance (default: this
            process's arguments).
        produced_by: the command that ran this evaluation when it is not ``unicorn-eval`` itself, recorded beside
            ``command``.
    """
    # heavy imports here: --help and argument errors stay fast
    from unicorn.evaluation import format_table, get_protocol
    from unicorn.evaluation.session import EVAL_OPTION_NAMES, check_request, evaluate_to_folder, overflow_note
    from unicorn.io import load_model
    from unicorn.io.provenance import command_line, provenance
    from unicorn.io.run_folder import run_dataset, run_of_checkpoint
    from unicorn.metrics.sampling import check_point_count

    num_points = _mesh_settings(args)["num_points"]
    check_point_count(f"--num-points {num_points}", num_points)
    check_point_count(f"--shape-points {args.shape_points}", args.shape_points)
    check_picture_sizes(args)
    device = parse_device(args.device)
    run_dir = run_of_checkpoint(args.checkpoint)
    named = args.dataset or (run_dataset(run_dir) or {}).get("name")  # the dataset, when known before loading
    early = _out_dir(args, run_dir, named)
    if early is not None:  # before the model is read: a mistake fails fast
        check_out_folder(early, args.overwrite)
    if named in DATASETS:  # the baselines the dataset's protocol cannot serve, named as the options given
        check_request(named, args.mean_shape, args.own_mean_shape, EVAL_OPTION_NAMES)
    level = args.template_level if args.template_level is not None else _protocol_level(named)
    overrides = {"template": {"level": level}} if level is not None else None
    model, info = load_model(args.checkpoint, map_location=device, overrides=overrides, trust=args.trust_checkpoint)
    log.info("loaded %s", info.describe())
    target = _target(args, info)
    out = _out_dir(args, info.run_dir, target.dataset)
    if out != early:
        check_out_folder(out, args.overwrite)
    check_request(target.dataset, args.mean_shape, args.own_mean_shape, EVAL_OPTION_NAMES)
    average = info.average_texture if args.average_texture == "auto" else args.average_texture == "on"
    options = _options(args, target.dataset, average)
    if device.type == "cpu" and get_protocol(options.protocol).meshes is not None and options.icp_iterations > 30:
        # the ICP's nearest-neighbour searches dominate (docs/performance.md, "Evaluation")
        print(
            f"note: {options.num_points} points and {options.icp_iterations} ICP iterations per image (the full "
            "protocol, 100k and 100, takes seconds of CPU time per image); --fast (UNICORN's validation setting) "
            "is much quicker",
            flush=True,
        )
    extra = {"produced_by": produced_by} if produced_by else {}
    meta = {
        **provenance(command or command_line("unicorn-eval", sys.argv[1:]), args.checkpoint, **extra),
        "checkpoint_format": info.format,
        "epoch": info.epoch,
        "step": info.step,
    }
    with overflow_note("unicorn-eval"):  # once, instead of the renderer's warning
        result, paths = evaluate_to_folder(
            model,
            target,
            options,
            out,
            meta,
            mean_shape_iterations=args.mean_shape,
            view_size=args.view_size,
            turntable_frames=args.turntable_frames,
            title=f"{target.dataset} ({args.split}): {Path(args.checkpoint).name}",
            device=device,
            overwrite=args.overwrite,
        )
    print(format_table(result.table, result.columns))
    per_image = result.seconds / max(1, len(result.per_image))
    print(f"\n{len(result.per_image)} images in {result.seconds:.1f} s ({per_image:.3f} s/image)")
    for name in ("csv", "json", "per_image", "html", "png"):
        if name in paths:
            print(f"{name:>9}: {paths[name]}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Console entry point; errors the user can fix are reported in one line with exit status 2."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    check_ranges(parser, args)
    check_common_arguments(parser, args)
    return report_errors("unicorn-eval", lambda: _run(args, argv), args.debug)


def _run(args: argparse.Namespace, argv: list[str] | None) -> int:
    from unicorn.registry import load_plugins

    tune_allocator()
    apply_common_arguments(args)
    load_plugins()  # UNICORN_PLUGINS and the unicorn.plugins entry points: their datasets and renderers
    if args.dataset is not None and args.dataset not in DATASETS:
        raise UsageError(f"--dataset: unknown dataset {args.dataset!r}; known: {DATASETS.names()}")
    _categories(args.categories)
    if args.dataset is not None:  # the options --dataset refuses, before the model is read
        check_categories_option(args.dataset, args.categories)
        if args.dataset != "lsun":
            lsun_tag(args.dataset, args.tag)
    from unicorn.io.provenance import command_line

    return run(args, command=command_line("unicorn-eval", sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
