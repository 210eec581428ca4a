"""The synthetic sets the test fixtures generate, also made beforehand for machines that cannot make them.

Generating a synthetic set needs open3d (its ray casting); reading one does not. On a machine without open3d (a
GPU image that runs ``benchmarks/gpu_checks.sh``) the fixtures copy each set from ``$UNICORN_TEST_DATA/<name>``,
written beforehand, from the same checkout, on a machine with open3d:

    python -m tests.support.prepared DIR

Without ``UNICORN_TEST_DATA`` (CI, a development install) the fixtures generate their sets.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

ENV = "UNICORN_TEST_DATA"
IMAGE_SIZE = 32  # the evaluation fixtures' image side


def _nmr(out: Path) -> Path:
    """NMR mode: 2 categories x 3 models x 6 views (also the ShapeNet-NMR fixture)."""
    from unicorn.data.synthetic.writer import generate_synthetic_dataset

    return generate_synthetic_dataset(
        out, ["chair", "car"], "nmr", n_models=3, seed=0, n_views=6, n_points=600, progress=False
    )


def _wild(out: Path) -> Path:
    """Wild mode (off-centre cameras, roll, random backgrounds)."""
    from unicorn.data.synthetic.writer import generate_synthetic_dataset

    return generate_synthetic_dataset(
        out, ["airplane", "lamp"], "wild", n_models=3, seed=1, n_views=6, n_points=600, progress=False
    )


def _eval_nmr(out: Path) -> Path:
    """NMR mode: 2 categories x 3 models x 2 views at 32 px (train split: 2 models per category)."""
    from unicorn.data.synthetic.writer import generate_synthetic_dataset

    return generate_synthetic_dataset(
        out, ["chair", "mug"], "nmr", n_models=3, seed=0, image_size=IMAGE_SIZE, n_views=2, n_points=600, progress=False
    )


def _cache(out: Path) -> Path:
    """A cache (``UNICORN_CACHE``) holding the 5-model chair set at 32 px that the training tests use."""
    from unicorn.data.synthetic import ensure_synthetic_dataset

    ensure_synthetic_dataset(
        root=out / "synthetic_32px", category="chair", mode="nmr", n_models=5, seed=0, image_size=32, progress=False
    )
    return out


#: every generated set of the fixtures, by name
SETS: dict[str, Callable[[Path], Path]] = {"nmr": _nmr, "wild": _wild, "eval-nmr": _eval_nmr, "cache": _cache}


def generated(name: str, out: Path) -> Path:
    """The set ``name`` of :data:`SETS` in the folder ``out``: copied from ``$UNICORN_TEST_DATA/<name>`` where that
    holds it, else generated."""
    source = os.environ.get(ENV)
    if source and (Path(source) / name).is_dir():
        shutil.copytree(Path(source) / name, out, dirs_exist_ok=True)
        return out
    return SETS[name](out)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m tests.support.prepared DIR", file=sys.stderr)
        return 2
    folder = Path(args[0])
    for name, make in SETS.items():
        if (folder / name).exists():
            shutil.rmtree(folder / name)  # made again: from this checkout's generator
        make(folder / name)
        print(f"{folder / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
