"""A training run's folder: what a run writes there, resuming from it, and refusing to overwrite an earlier run.

A folder that already holds a run is only trained in again to resume it (``ckpt_path=last``) or with
``overwrite=true`` (its outputs are deleted first); ``unicorn-train`` (:mod:`unicorn.cli.train`) applies these rules.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from unicorn.errors import UserError
from unicorn.io.serialization import check_checkpoint_path

__all__ = [
    "RUN_OUTPUTS",
    "RunFolderError",
    "holds_nothing",
    "prepare_folder",
    "previous_run",
    "resolve_ckpt",
    "run_dataset",
    "run_of_checkpoint",
]

log = logging.getLogger("unicorn.train")

#: what a run writes into its folder (besides Hydra's ``.hydra/`` and ``train.log``, and ``config.yaml``)
RUN_OUTPUTS = ("checkpoints", "csv", "tensorboard", "images", "eval", "heldout.csv")


class RunFolderError(UserError, FileExistsError):
    """A new run was started in a folder that already holds one."""


def resolve_ckpt(ckpt_path: str | None, checkpoint_dir: Path) -> str | None:
    """``None``, ``"last"`` (this run directory's last.ckpt if it exists) or an existing file."""
    if ckpt_path is None:
        return None
    if ckpt_path == "last":
        last = checkpoint_dir / "last.ckpt"
        if last.is_file():
            return str(last)
        log.info("ckpt_path=last: no %s yet, training from scratch", last)
        return None
    return str(check_checkpoint_path(Path(ckpt_path).expanduser().resolve(), "ckpt_path"))


def previous_run(output_dir: Path) -> Path | None:
    """The first output of an earlier run found in ``output_dir`` (a checkpoint, a metric log...), or None."""
    checkpoints = output_dir / "checkpoints"
    if checkpoints.is_dir():
        found = next((p for p in sorted(checkpoints.iterdir()) if p.suffix == ".ckpt"), None)
        if found is not None:
            return found
    for name in RUN_OUTPUTS[1:]:
        path = output_dir / name
        if path.is_file() or (path.is_dir() and any(path.iterdir())):
            return path
    return None


def prepare_folder(output_dir: Path, resume: bool, overwrite: bool) -> None:
    """Refuse to start a new run over an earlier one, or delete the earlier one's outputs when told to.

    Raises:
        RunFolderError: ``output_dir`` holds a run and neither ``resume`` nor ``overwrite`` is set.
    """
    previous = previous_run(output_dir)
    if previous is None or resume:
        return
    if not overwrite:
        raise RunFolderError(
            f"{output_dir} already holds a run ({previous.relative_to(output_dir)}); resume it with "
            "ckpt_path=last, replace it with overwrite=true, or train elsewhere (hydra.run.dir=...)"
        )
    log.warning("overwrite=true: deleting the earlier run's outputs in %s", output_dir)
    for name in RUN_OUTPUTS:
        path = output_dir / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def holds_nothing(folder: Path) -> bool:
    """Whether ``folder`` holds only what Hydra and ``unicorn-train``'s build write before training (or does not
    exist): such a folder can be removed again when the run fails before training."""
    if not folder.is_dir():
        return True
    return all(p.name in (".hydra", "train.log", "config.yaml") for p in folder.iterdir())


def run_of_checkpoint(path: Path) -> Path | None:
    """The run folder a checkpoint sits in (``<run>/checkpoints/x.ckpt`` -> ``<run>``), or None."""
    return path.parent.parent if path.parent.name == RUN_OUTPUTS[0] else None


def run_dataset(run_dir: Path | None) -> dict[str, Any] | None:
    """The ``dataset`` group of ``<run>/config.yaml`` (written by ``unicorn-train``), if any."""
    if run_dir is None or not (run_dir / "config.yaml").is_file():
        return None
    import yaml

    try:
        cfg = yaml.safe_load((run_dir / "config.yaml").read_text()) or {}
    except yaml.YAMLError:
        return None
    dataset = cfg.get("dataset") if isinstance(cfg, Mapping) else None
    return dict(dataset) if isinstance(dataset, Mapping) else None
