"""The options that ``unicorn-eval`` and ``unicorn-reconstruct`` share: the help format, checkpoint trust, image
limits, ``--overwrite`` with its output-folder check, picture sizes and ``--device``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from unicorn.cli.errors import UsageError, add_debug_argument, whole_number

__all__ = [
    "HelpFormatter",
    "add_common_arguments",
    "add_overwrite_argument",
    "apply_common_arguments",
    "check_common_arguments",
    "check_out_folder",
    "check_ranged_options",
    "check_picture_sizes",
    "lsun_tag",
    "parse_device",
]


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default only when it says something (not None or False)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    """The options every checkpoint-reading tool shares: trust, image pixel and byte limits, debug."""
    p.add_argument(
        "--trust-checkpoint",
        action="store_true",
        help="read a checkpoint that needs full unpickling (it can run code: only for files you trust)",
    )
    add_image_limit_arguments(p)
    add_debug_argument(p)


def add_image_limit_arguments(p: argparse.ArgumentParser) -> None:
    """``--max-image-pixels`` and ``--max-image-bytes``, the limits every image-reading tool takes
    (:func:`check_common_arguments`, :func:`apply_common_arguments`)."""
    p.add_argument(
        "--max-image-pixels",
        type=whole_number,
        help="refuse images with more pixels (decompression bombs); 0: no limit; default: "
        "$UNICORN_MAX_IMAGE_PIXELS or 178956970",
    )
    p.add_argument(
        "--max-image-bytes",
        type=whole_number,
        help="refuse images whose decoded array has more bytes (width x height x 12 for float32 RGB); 0: no limit; "
        "default: $UNICORN_MAX_IMAGE_BYTES or 1073741824",
    )


def add_overwrite_argument(p: argparse.ArgumentParser, what: str) -> None:
    """Add ``--overwrite``: write into a non-empty ``--out`` (:func:`check_out_folder`); ``what``: when the files
    are replaced."""
    p.add_argument(
        "--overwrite",
        action="store_true",
        help=f"write into a non-empty --out (same-named files are replaced, {what})",
    )


def check_out_folder(out: Path, overwrite: bool) -> None:
    """Refuse an output folder that is a file, that holds files when ``--overwrite`` is not given, or that cannot
    be written (:func:`unicorn.io.staging.check_writable`).

    Raises:
        UsageError: the message names the folder and the option.
        OSError: the folder cannot be written (the message names it).
    """
    from unicorn.io.staging import check_writable

    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise UsageError(f"--out {out} is not empty; choose another folder or pass --overwrite to write into it")
    check_writable(out)


def check_categories_option(dataset: str, categories: Any) -> None:
    """Refuse ``--categories`` (given: not None) for a dataset whose items are not picked by category
    (:attr:`unicorn.data.registry.DatasetSpec.by_category`), where it would be ignored.

    Raises:
        UsageError: the message names the dataset.
    """
    from unicorn.data.registry import DATASETS

    if categories is not None and dataset in DATASETS and not DATASETS.get(dataset).by_category:
        raise UsageError(f"--categories picks ShapeNet or synthetic categories; {dataset} has none: drop --categories")


def check_common_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse negative image limits (a usage error)."""
    for name in ("max_image_pixels", "max_image_bytes"):
        if (getattr(args, name) or 0) < 0:
            parser.error(f"--{name.replace('_', '-')} must be >= 0")


def check_picture_sizes(args: argparse.Namespace) -> None:
    """Refuse pictures above the render memory limit before any is made: one RGBA view of ``--view-size``, and
    the ``--turntable-frames`` frames of a turntable at that size, held together until its GIF is written, and
    likewise the ``--strip-views`` views of a strip where the command has one (float32;
    ``UNICORN_MAX_RENDER_BYTES``, the limit of the renders they are made of).

    Raises:
        unicorn.checks.SizeLimitError: the message names the option and the limit.
    """
    from unicorn.checks import check_limit
    from unicorn.render import MAX_RENDER_BYTES_ENV, max_render_bytes

    size, frames = args.view_size, args.turntable_frames
    limit, source = max_render_bytes(), f"{MAX_RENDER_BYTES_ENV}; 0: no limit"
    picture = 4 * size * size * 4
    check_limit(f"--view-size {size}", f"a picture: 4 x {size} x {size} float32", picture, limit, "bytes", source)
    # the two options together: either may be the one to lower
    what = f"a turntable's frames: {frames} x 4 x {size} x {size} float32"
    setting = f"--turntable-frames {frames} at --view-size {size}"
    check_limit(setting, what, frames * picture, limit, "bytes", source)
    views = getattr(args, "strip_views", None)
    if views is not None:
        what = f"a strip's views: {views} x 4 x {size} x {size} float32"
        check_limit(f"--strip-views {views} at --view-size {size}", what, views * picture, limit, "bytes", source)


def apply_common_arguments(args: argparse.Namespace) -> None:
    """Refuse a ``--device`` this machine lacks, where the command has the option (:func:`parse_device`: before
    any input is read), and set the image limits given on the command line for this process and its workers.

    Raises:
        UsageError: the ``--device``.
    """
    from unicorn.data.images import set_max_image_bytes, set_max_image_pixels

    if getattr(args, "device", None) is not None:
        parse_device(args.device)

    if args.max_image_pixels is not None:
        set_max_image_pixels(args.max_image_pixels)
    if args.max_image_bytes is not None:
        set_max_image_bytes(args.max_image_bytes)


def parse_device(name: str) -> Any:
    """The ``torch.device`` that ``--device`` names (``auto``: CUDA when available, else the CPU).

    Raises:
        UsageError: not a device, or one this machine lacks (a CUDA index beyond its devices included).
    """
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise UsageError(f"--device {name!r} is not a device; use 'auto', 'cpu', 'cuda' or 'cuda:N'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"--device {name}: CUDA is not available on this machine; use --device cpu")
    count = torch.cuda.device_count() if device.type == "cuda" else 0
    if device.index is not None and device.type == "cuda" and device.index >= count:
        have = "cuda:0" if count == 1 else f"cuda:0 to cuda:{count - 1}"
        raise UsageError(f"--device {name}: this machine has {count} CUDA device(s), {have}")
    backend = getattr(torch, device.type, None)  # torch.mps, torch.xpu...: each says whether it is there
    if device.type not in ("cpu", "cuda") and not getattr(backend, "is_available", lambda: False)():
        raise UsageError(f"--device {name}: {device.type} is not available on this machine; use 'cpu' or 'auto'")
    return device


def lsun_tag(dataset: str, tag: str | None, known: str | None = None, hint: str = "") -> str | None:
    """The LSUN category a command reads for ``dataset``: ``--tag`` (``tag``), else ``known`` (a training run's);
    None for another dataset.

    Raises:
        UsageError: ``--tag`` for another dataset, or ``lsun`` without a category (``hint``: what else names one).
    """
    if dataset != "lsun":
        if tag is not None:
            raise UsageError(f"--tag is for lsun only (the LSUN category), not {dataset}")
        return None
    if tag is None and known is None:
        raise UsageError(f"lsun needs --tag, the LSUN category whose folder is under --root (horse, motorbike){hint}")
    return tag if tag is not None else known


def check_ranged_options(
    parser: argparse.ArgumentParser, args: argparse.Namespace, ranged: dict[str, tuple[type, str]]
) -> None:
    """Refuse an option's value outside the range its setting declares (:func:`unicorn.model.ranges.ranged`), as a
    usage error naming the option, before anything is read.

    Args:
        parser: the command's parser (its usage error).
        args: the parsed options.
        ranged: option (its ``args`` name) -> (the settings class, the field that declares the range).
    """
    from unicorn.model.ranges import describe_range, field_range

    for name, (schema, field) in ranged.items():
        low, high = field_range(schema, field)
        value = getattr(args, name)
        if value is not None and not ((low is None or value >= low) and (high is None or value <= high)):
            parser.error(f"--{name.replace('_', '-')} must be {describe_range(low, high)}")
