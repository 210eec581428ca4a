"""Files shipped with the package (ground floor, free of torch: ``unicorn-train --help`` reads it first)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["config_dir"]


def config_dir() -> Path:
    """Absolute path of the shipped configs: ``unicorn/conf`` in a wheel, else the checkout's ``conf/``.

    Raises:
        FileNotFoundError: neither holds ``train.yaml``.
    """
    package = Path(__file__).resolve().parent  # .../unicorn
    candidates = [package / "conf", package.parent.parent / "conf"]  # wheel; src/unicorn -> repository root
    for path in candidates:
        if (path / "train.yaml").is_file():
            return path
    raise FileNotFoundError(f"unicorn's configs (train.yaml) not found in {[str(p) for p in candidates]}")
