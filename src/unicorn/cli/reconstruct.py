"""``unicorn-reconstruct``: images in, a textured mesh, pictures, mask, pose and turntable per image out.

Examples::

    unicorn-reconstruct car_big.pkl photos/ --out reconstructions
    unicorn-reconstruct outputs/cub/runs/<time>/checkpoints/last.ckpt bird.png --device cuda
    unicorn-reconstruct model.pkl car.jpg --bbox 40,80,600,420 --out car
    unicorn-reconstruct model.pkl car.jpg --refine 50 --out car     # fitted to the photo, 50 steps

Every image is framed as the training images were (a transparent PNG is cropped around its opaque pixels, a
``--bbox`` crops around the box, anything else is fitted and padded to a square), then reconstructed; see
:mod:`unicorn.evaluation.reconstruct` for the files written per image.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from unicorn import __version__
from unicorn.cli.errors import UsageError, folder_path, report_errors, whole_number
from unicorn.cli.options import (
    HelpFormatter,
    add_common_arguments,
    add_overwrite_argument,
    apply_common_arguments,
    check_common_arguments,
    check_out_folder,
    check_picture_sizes,
    check_ranged_options,
    parse_device,
)
from unicorn.errors import UnicornWarning
from unicorn.io.images import DEFAULT_PADDING, MAX_PADDING
from unicorn.model.config import TemplateConfig

if TYPE_CHECKING:
    from unicorn.objectives.refine import RefineOptions

__all__ = ["build_parser", "main"]

log = logging.getLogger("unicorn.reconstruct")


class SkippedInputWarning(UnicornWarning, RuntimeWarning):
    """An input image that ``--skip-bad`` skips (logged in one line, :func:`unicorn.cli.errors.log_warnings`; still
    a ``RuntimeWarning``, as it was)."""


def _bbox(text: str) -> list[float]:
    """Four numbers; whether they make a box on the image is :func:`unicorn.io.images.check_box`'s to say."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4:
        raise argparse.ArgumentTypeError(f"must be four numbers x1,y1,x2,y2, got {text!r}")  # after "--bbox: "
    return values


#: most views of a turntable strip: one every 15 degrees (the strip and the overview's rows are that many pictures
#: wide, and viewers and browsers do not open pictures of any width)
MAX_STRIP_VIEWS = 24


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="unicorn-reconstruct",
        description="Reconstruct images with a UNICORN checkpoint (unicorn-train .ckpt, released .pkl or "
        "unicorn.io.save_model file): per image a textured mesh (OBJ + MTL + PNG, GLB), the reconstruction, the "
        "predicted mask and pose, and a turntable (GIF and PNG strip).",
        formatter_class=HelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s (unicorn3d) {__version__}")
    p.add_argument("checkpoint", help="checkpoint file")
    p.add_argument("inputs", nargs="+", help="image files and/or folders (searched recursively)")
    p.add_argument("--out", type=folder_path, default=Path("reconstructions"), help="output folder")
    p.add_argument("--device", default="auto", help="'auto' (CUDA when available), 'cpu', 'cuda' or 'cuda:N'")
    p.add_argument("--batch-size", type=whole_number, default=16, help="images per forward pass")
    p.add_argument("--view-size", type=whole_number, default=256, help="side of the pictures")
    p.add_argument("--turntable-frames", type=whole_number, default=24, help="frames of turntable.gif (0: no GIF)")
    p.add_argument(
        "--strip-views", type=whole_number, default=4, help=f"views in turntable.png (at most {MAX_STRIP_VIEWS})"
    )
    p.add_argument(
        "--bbox",
        type=_bbox,
        metavar="X1,Y1,X2,Y2",
        help="object box x1,y1,x2,y2: 0-based pixels, both corners inclusive, of the photo turned upright by its EXIF "
        "orientation (one input image only)",
    )
    p.add_argument(
        "--padding",
        type=float,
        default=DEFAULT_PADDING,
        help="margin added on every side of the object's box (a --bbox, or an alpha cut-out's opaque pixels) before "
        f"it is squared, as a fraction of the box's width and height (at most {MAX_PADDING:g})",
    )
    p.add_argument("--no-alpha-crop", action="store_true", help="do not crop transparent images to their object")
    p.add_argument("--template-level", type=whole_number, help="icosphere level of the mesh (3: 642 vertices, 4: 2562)")
    p.add_argument(
        "--average-texture",
        choices=("auto", "on", "off"),
        default="auto",
        help="mean-colour textures; auto: as the checkpoint was being trained",
    )
    p.add_argument(
        "--refine",
        type=whole_number,
        default=0,
        metavar="STEPS",
        help="refine each prediction against its image for this many steps (0: the network's prediction); the "
        "exports carry the refined result, the report shows the network's beside it",
    )
    p.add_argument(
        "--refine-parts",
        default="default",
        help="what --refine optimises: 'default' (codes, texture, vertices), 'all' or comma-separated codes, "
        "texture, vertices, pose",
    )
    p.add_argument("--skip-bad", action="store_true", help="skip unreadable images with a warning")
    add_overwrite_argument(p, "once every image is reconstructed")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_common_arguments(p)
    return p


def run(args: argparse.Namespace, command: str | None = None) -> int:
    """Reconstruct as ``args`` say; returns the exit status (``command``: the command line to record)."""
    from unicorn.data.images import ImageLoadError
    from unicorn.evaluation.reconstruct import OPTIONAL_FILES, check_free, earlier_folders, reconstruct, unique_names
    from unicorn.evaluation.session import overflow_note
    from unicorn.io import collect_inputs, frame_input, load_model, read_input
    from unicorn.io.images import check_padding
    from unicorn.io.provenance import command_line, provenance
    from unicorn.io.staging import staged_folder

    check_padding(args.padding, "--padding")
    if args.strip_views > MAX_STRIP_VIEWS:
        raise UsageError(f"--strip-views must be at most {MAX_STRIP_VIEWS} (one view every 15 degrees)")
    check_picture_sizes(args)
    refine_options = _refine_options(args)
    out = args.out.expanduser()
    check_out_folder(out, args.overwrite)
    files = collect_inputs(args.inputs, leave_out=out)
    if args.bbox is not None and len(files) != 1:
        raise UsageError(f"--bbox needs exactly one input image, got {len(files)}")
    # decode every image once before loading the model, so that input mistakes fail fast (they are read again
    # below rather than kept: a folder of full-size photos would not fit in memory)
    readable = []
    for path in files:
        try:
            read_input(path, args.bbox, not args.no_alpha_crop)
        except ImageLoadError as err:
            if not args.skip_bad:
                raise
            warnings.warn(f"skipping {err}", SkippedInputWarning, stacklevel=1)
            continue
        readable.append(path)
    if not readable:
        raise UsageError("none of the inputs could be read")
    readable = list(zip(readable, unique_names(readable)))  # the names of the images read only
    # an entry of --out that the outputs cannot replace (a file where an image's folder goes): refused now, not once
    # every image is reconstructed (check_out_folder refused a non-empty --out without --overwrite)
    check_free(out, [name for _, name in readable], overwrite=True)
    # --overwrite with other images: the earlier ones' folders stay (not ours to delete), named as left out of the index
    earlier = earlier_folders(out, [name for _, name in readable])
    device = parse_device(args.device)
    overrides = {"template": {"level": args.template_level}} if args.template_level is not None else None
    model, info = load_model(args.checkpoint, map_location=device, overrides=overrides, trust=args.trust_checkpoint)
    log.info("loaded %s", info.describe())
    size = model.config["image_size"]
    items = [
        frame_input(read_input(path, args.bbox, not args.no_alpha_crop), size, name, args.padding)
        for path, name in readable
    ]
    average = info.average_texture if args.average_texture == "auto" else args.average_texture == "on"
    start = time.perf_counter()
    # a failure part-way leaves --out as it was; the renders' overflow is said once, not by the renderer
    with overflow_note("unicorn-reconstruct"), staged_folder(out, OPTIONAL_FILES, merge=args.overwrite) as staging:
        records = reconstruct(
            model,
            items,
            staging,
            device=device,
            batch_size=args.batch_size,
            view_size=args.view_size,
            turntable_frames=args.turntable_frames,
            strip_views=args.strip_views,
            average_texture=average,
            progress=not args.quiet,
            provenance=provenance(command or command_line("unicorn-reconstruct", sys.argv[1:]), args.checkpoint),
            refine_options=refine_options,
            earlier=earlier,
        )
    seconds = time.perf_counter() - start
    print(f"{len(records)} images reconstructed in {seconds:.1f} s ({seconds / len(records):.2f} s/image) on {device}")
    print(f"outputs in {out}/<image>/ ; overview: {out / 'overview.png'}, {out / 'index.html'}")
    if earlier:
        listed = ", ".join(earlier[:5]) + (f" and {len(earlier) - 5} more" if len(earlier) > 5 else "")
        print(
            f"not in the overview: {len(earlier)} image folder(s) of an earlier reconstruction left in {out}: {listed}"
        )
    return 0


def _refine_options(args: argparse.Namespace) -> RefineOptions | None:
    """The :class:`~unicorn.objectives.refine.RefineOptions` of ``--refine`` and ``--refine-parts`` (None: no
    refinement).

    Raises:
        UsageError: an unknown part, or more steps than :data:`unicorn.objectives.refine.MAX_STEPS`.
    """
    from unicorn.objectives.refine import RefineOptions, RefineOptionsError, parse_parts

    try:
        parts = parse_parts(args.refine_parts)
    except RefineOptionsError as err:
        raise UsageError(f"--refine-parts: {err}") from None
    if args.refine <= 0:
        if args.refine_parts != "default":
            raise UsageError("--refine-parts needs --refine STEPS (how many refinement steps)")
        return None
    try:
        return RefineOptions(steps=args.refine, parts=parts, progress=not args.quiet)
    except RefineOptionsError as err:
        raise UsageError(f"--refine {args.refine}: {err}") from None


def _negative_boxes(argv: Sequence[str]) -> list[str]:
    """``argv`` with ``--bbox -5,10,200,300`` joined into ``--bbox=-5,10,200,300``: argparse takes a value starting
    with ``-`` for an option unless it is one negative number, and a detector's box may start left of the image."""
    joined: list[str] = []
    values = iter(argv)
    for arg in values:
        if arg == "--":
            joined += [arg, *values]
            break
        following = next(values, None) if arg == "--bbox" else None
        if following is not None and re.match(r"-[\d.]", following):
            joined.append(f"--bbox={following}")
        else:
            joined += [arg] if following is None else [arg, following]
    return joined


def main(argv: list[str] | None = None) -> int:
    """Console entry point; errors the user can fix are reported in one line with exit status 2."""
    parser = build_parser()
    args = parser.parse_args(_negative_boxes(sys.argv[1:] if argv is None else argv))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in ("batch_size", "view_size", "strip_views"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    for name in ("turntable_frames", "refine"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} must be >= 0")
    check_ranged_options(parser, args, {"template_level": (TemplateConfig, "level")})
    check_common_arguments(parser, args)
    return report_errors("unicorn-reconstruct", lambda: _run(args, argv), args.debug)


def _run(args: argparse.Namespace, argv: list[str] | None) -> int:
    from unicorn.registry import load_plugins

    apply_common_arguments(args)
    load_plugins()  # UNICORN_PLUGINS and the unicorn.plugins entry points: a plugin's renderer in a checkpoint
    from unicorn.io.provenance import command_line

    return run(args, command=command_line("unicorn-reconstruct", sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
