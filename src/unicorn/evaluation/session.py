"""One evaluation into a folder: a dataset's protocol on a model in memory, the metrics and the visual report.

:func:`evaluate_to_folder` is what ``unicorn-eval`` runs after loading a checkpoint, and what ``unicorn-train``
runs on the model it just trained (``evaluate.enabled``), without re-reading it from disk.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from unicorn.config.schema import REPORT_TURNTABLE_FRAMES, EvaluateConfig
from unicorn.data.common import OnError
from unicorn.errors import UserError
from unicorn.evaluation.baselines import category_point_clouds
from unicorn.evaluation.evaluator import build_eval_dataset, evaluate
from unicorn.evaluation.interface import EvaluableModel
from unicorn.evaluation.mean_shape import fit_mean_shapes
from unicorn.evaluation.metric_files import write_metrics
from unicorn.evaluation.protocols import EvalOptions, EvaluationResult, get_protocol, protocol_for
from unicorn.evaluation.report import REPORT_FILES, write_report
from unicorn.io.staging import staged_folder
from unicorn.render import OverflowCounter

__all__ = [
    "EVAL_OPTION_NAMES",
    "EvalRequestError",
    "EvalTarget",
    "check_request",
    "eval_command",
    "evaluate_to_folder",
    "overflow_note",
    "served_settings",
    "settings_options",
]

log = logging.getLogger(__name__)


@dataclass
class EvalTarget:
    """What to evaluate on: a dataset split.

    Attributes:
        dataset: a registered dataset name (:func:`unicorn.data.registry.list_datasets`).
        root: its folder (for ``synthetic``: the generated dataset, which holds ``metadata.yaml``).
        split: ``"train"``, ``"val"`` or ``"test"``.
        categories: ShapeNet / synthetic categories, None for all.
        max_images: at most this many items, spread evenly over the split; None for all.
        on_error: ``"raise"``: an unreadable image is an error; ``"skip"``: it is left out with a warning
            (``unicorn-eval --skip-bad``; the evaluation after training takes the dataset's ``on_error``).
        dataset_options: the training run's dataset options; those that say which data it read (LSUN's ``tag``)
            are kept (:func:`~unicorn.evaluation.build_eval_dataset`).
    """

    dataset: str
    root: str
    split: str = "test"
    categories: str | list[str] | None = None
    max_images: int | None = None
    on_error: OnError = "raise"
    dataset_options: Mapping[str, Any] = field(default_factory=dict)


def settings_options(settings: Any, dataset: str, **options: Any) -> EvalOptions:
    """The evaluation options of shared evaluation settings for ``dataset``'s protocol; ``options`` sets the others
    (e.g. ``average_texture``).

    Args:
        settings: an object with the attributes of :class:`unicorn.config.schema.EvalSettings` (a subclass, or the
            held-out callback); its ``report_samples`` is taken where it has one.
    """
    shared = ("batch_size", "num_points", "icp_iterations", "own_mean_shape", "shape_points", "report_samples")
    values = {name: getattr(settings, name) for name in shared if hasattr(settings, name)}
    return EvalOptions(protocol=protocol_for(dataset), **values, **options)


#: the side of the report's pictures of the evaluation after training (``unicorn-eval --view-size``)
AFTER_TRAINING_VIEW_SIZE = 256


def eval_command(
    checkpoint: Path,
    out: Path,
    settings: EvaluateConfig,
    template_level: int | None = None,
    skip_bad: bool = False,
    view_size: int = AFTER_TRAINING_VIEW_SIZE,
) -> str:
    """The ``unicorn-eval`` command that evaluates ``checkpoint`` into ``out`` as ``settings`` say (a provenance
    record of the evaluation after training), on the mesh of ``template_level`` when given (the trained model's:
    ``unicorn-eval`` would take the protocol's, :attr:`~unicorn.evaluation.protocols.Protocol.template_level`),
    skipping unreadable images with ``skip_bad`` (a dataset with ``on_error: skip``), its report's pictures
    ``view_size`` pixels wide."""
    from unicorn.io.provenance import command_line

    s = settings
    argv = [str(checkpoint), f"--split={s.split}", f"--out={out}", f"--num-points={s.num_points}"]
    argv += [f"--icp-iterations={s.icp_iterations}", f"--batch-size={s.batch_size}"]
    argv += [f"--report-samples={s.report_samples}", f"--turntable-frames={s.turntable_frames}"]
    argv += [f"--view-size={view_size}"]  # unicorn-eval's default differs from the evaluation after training's
    argv += [f"--mean-shape={s.mean_shape_iterations}"] + (["--own-mean-shape"] if s.own_mean_shape else [])
    argv += [f"--shape-points={s.shape_points}"]
    argv += [f"--max-images={s.max_images}"] if s.max_images is not None else []
    argv += [f"--template-level={template_level}"] if template_level is not None else []
    argv += ["--skip-bad"] if skip_bad else []
    return command_line("unicorn-eval", argv)


def evaluate_to_folder(
    model: EvaluableModel,
    target: EvalTarget,
    options: EvalOptions,
    out: Path,
    meta: Mapping[str, Any],
    *,
    mean_shape_iterations: int = 0,
    view_size: int = AFTER_TRAINING_VIEW_SIZE,
    turntable_frames: int = REPORT_TURNTABLE_FRAMES,
    title: str | None = None,
    device: torch.device | str | None = None,
    overwrite: bool = True,
) -> tuple[EvaluationResult, dict[str, Path]]:
    """Evaluate ``model`` on ``target`` with ``options`` and write the metrics (CSV, JSON) and the report into ``out``.

    Args:
        model: the model (moved to ``device``, put in eval mode).
        target: the dataset split.
        options: the evaluation settings; ``options.protocol`` must be the dataset's.
        out: the output folder (created); the files appear in it only when all are written
            (:func:`unicorn.io.staging.staged_folder`), replacing same-named ones.
        meta: provenance written with the metrics (command, checkpoint, ...); the target and the options are added.
        mean_shape_iterations: > 0: fit each category's mean shape to its training shapes for that many
            iterations and score it beside the model on the category's objects (``shape-win``; the shapenet
            protocol only; not fitted, with a warning, when ``options.icp_iterations`` is 0: it is scored after
            ICP).
        view_size, turntable_frames: the report's render size and turntable length.
        title: the report's title (default: dataset and split).
        device: where to evaluate (default: the model's device).
        overwrite: False: ``out`` must still be missing or empty when the files move (checked by the caller before
            the evaluation, it may have been written since).

    Returns:
        the result and the written files by kind (``csv``, ``json``, ``per_image``, ``html``, ``png``).

    Raises:
        ValueError: a protocol that does not match the dataset, or a mean shape asked where there are no
            training point clouds.
    """
    _check_request(target, options, mean_shape_iterations)
    if device is None:
        device = next(model.parameters()).device  # type: ignore[attr-defined]
    data = build_eval_dataset(
        target.dataset,
        target.root,
        target.split,
        img_size=model.config["image_size"],
        categories=target.categories,
        max_images=target.max_images,
        seed=options.seed,
        on_error=target.on_error,
        options=target.dataset_options,
    )
    log.info(
        "evaluating %d %s images of %s (%s protocol) on %s",
        len(data),
        target.split,
        target.dataset,
        options.protocol,
        device,
    )
    mean_shapes = _mean_shapes(model, target, mean_shape_iterations, options)
    result = evaluate(model, data, options, dataset_name=target.dataset, device=device, shape_baseline=mean_shapes)
    full_meta = {
        **meta,
        **dataclasses.asdict(target),
        "device": str(device),
        "options": dataclasses.asdict(options),
        "mean_shape_iterations": mean_shape_iterations,
    }
    # a failure while writing leaves ``out`` as it was; a report of an earlier evaluation goes where this one has
    # none, or fewer samples
    with staged_folder(out, REPORT_FILES, merge=overwrite) as staging:
        paths = write_metrics(result, staging, full_meta)
        if result.samples:
            log.info("writing the report: %d samples to %s", len(result.samples), out / "report.html")
            report = write_report(
                model,
                result,
                staging,
                title or f"{target.dataset} ({target.split})",
                full_meta,
                view_size=view_size,
                turntable_frames=turntable_frames,
                device=device,
            )
            paths.update(report)
    return result, {kind: Path(out) / path.relative_to(staging) for kind, path in paths.items()}


@contextmanager
def overflow_note(command: str) -> Iterator[OverflowCounter]:
    """Count the block's renders that had more candidate faces than the renderer's ``faces_per_pixel`` (in place of
    the renderer's warning) and log, once at its end, the share of pixels they make; nothing when there were none."""
    with OverflowCounter() as counter:
        yield counter
    if counter.overflow:
        log.warning(
            "note: %s: %s (faces_per_pixel is the checkpoint's renderer setting: renderer.faces_per_pixel in training)",
            command,
            counter.describe(),
        )


class EvalRequestError(UserError, ValueError):
    """Evaluation options the dataset cannot serve (a mean shape without training point clouds...)."""


#: how :func:`check_request` names the settings it checks in ``unicorn-eval``'s errors: its options
EVAL_OPTION_NAMES = {"mean_shape_iterations": "--mean-shape", "own_mean_shape": "--own-mean-shape"}


def check_request(
    dataset: str, mean_shape_iterations: int, own_mean_shape: bool, names: Mapping[str, str] | None = None
) -> None:
    """Refuse baselines that ``dataset``'s protocol cannot serve, before anything is read.

    Args:
        dataset: a registered dataset name.
        mean_shape_iterations: > 0: a mean shape fitted to the training shapes is asked for.
        own_mean_shape: the model's own average shape is asked for.
        names: how the error names each setting, by its name here (``mean_shape_iterations``, ``own_mean_shape``):
            :data:`EVAL_OPTION_NAMES` for ``unicorn-eval``, ``evaluate.<name>`` for a training config; a
            setting left out is named as here.

    Raises:
        EvalRequestError: names the setting given and the dataset.
    """
    name = {"mean_shape_iterations": "mean_shape_iterations", "own_mean_shape": "own_mean_shape", **(names or {})}
    unserved = _unserved(dataset, mean_shape_iterations, own_mean_shape)
    if "mean_shape_iterations" in unserved:
        raise EvalRequestError(
            f"{name['mean_shape_iterations']}: a mean shape needs a dataset with training point clouds (shapenet "
            f"protocol), not {dataset}"
        )
    if "own_mean_shape" in unserved:
        raise EvalRequestError(
            f"{name['own_mean_shape']}: the model's own average shape needs a dataset with ground-truth point clouds, "
            f"not {dataset}"
        )


def _unserved(dataset: str, mean_shape_iterations: int, own_mean_shape: bool) -> list[str]:
    """The baselines asked for (``mean_shape_iterations``, ``own_mean_shape``) that ``dataset``'s protocol cannot
    serve: a mean shape needs training point clouds, the model's own average shape ground-truth ones."""
    spec = get_protocol(protocol_for(dataset))
    asked = {"mean_shape_iterations": mean_shape_iterations > 0, "own_mean_shape": own_mean_shape}
    served = {"mean_shape_iterations": spec.training_clouds, "own_mean_shape": spec.meshes is not None}
    return [key for key in asked if asked[key] and not served[key]]


def served_settings(settings: EvaluateConfig, dataset: str) -> EvaluateConfig:
    """``settings`` without the baselines ``dataset``'s protocol cannot serve (:func:`check_request`), each one left
    out named in the log: the evaluation after training of a recipe run on another dataset
    (``experiment=synthetic dataset=folder``) scores what the dataset allows instead of failing once trained, as the
    held-out evaluation does."""
    why = {
        "mean_shape_iterations": (0, "no training point clouds for a mean shape"),
        "own_mean_shape": (False, "no ground-truth point clouds to score the model's own average shape"),
    }
    left_out = {key: why[key] for key in _unserved(dataset, settings.mean_shape_iterations, settings.own_mean_shape)}
    for key, (_, reason) in left_out.items():
        log.info("evaluation after training: evaluate.%s left out: %s has %s", key, dataset, reason)
    return dataclasses.replace(settings, **{key: value for key, (value, _) in left_out.items()})


def _check_request(target: EvalTarget, options: EvalOptions, mean_shape_iterations: int) -> None:
    """Refuse options the dataset's protocol cannot serve.

    Raises:
        EvalRequestError: the options' protocol is not the dataset's, or a baseline needs data the dataset lacks
            (:func:`check_request`).
    """
    protocol = protocol_for(target.dataset)
    if options.protocol != protocol:
        raise EvalRequestError(
            f"options.protocol is {options.protocol!r} but {target.dataset} is evaluated with {protocol!r}"
        )
    check_request(target.dataset, mean_shape_iterations, options.own_mean_shape)


def _mean_shapes(
    model: EvaluableModel, target: EvalTarget, iterations: int, options: EvalOptions
) -> dict[str, torch.Tensor] | None:
    """Per evaluation group (category), the mean shape (V, 3) of its training shapes on the model's template,
    fitted for ``iterations``; None for 0, or without ICP (the mean shape is only scored after it)."""
    if iterations <= 0:
        return None
    if options.icp_iterations <= 0:
        log.warning(
            "note: no mean shape is fitted (mean_shape_iterations %d): it is scored after ICP, and icp_iterations is 0",
            iterations,
        )
        return None
    clouds = category_point_clouds(target.root, target.categories, max_models=200, num_points=5000)
    shapes = ", ".join(f"{group} {len(group_clouds)}" for group, group_clouds in clouds.items())
    log.info("fitting the mean shape of each category's training shapes (%s; %d iterations each)", shapes, iterations)
    verts, faces = model.template.verts, model.template.faces
    return fit_mean_shapes(verts, faces, clouds, iterations=iterations, seed=options.seed)
