"""The synthetic sets the test fixtures generate, also made beforehand for machines that cannot make them.

Generating a synthetic set needs open3d (its ray casting); reading one does not. On a machine without open3d (a
GPU image that runs ``benchmarks/gpu_checks.sh``) the fixtures copy each set from ``$UNICORN_TEST_DATA/<name>``,
written beforehand, from the same checkout, on a machine with open3d:

    python -m tests.support.prepared DIR

A copy whose ``synthetic.json`` names another generator version or other settings than this checkout's
(:data:`SETS`) is refused, with the command that writes it again. Without ``UNICORN_TEST_DATA`` (CI, a
development install) the fixtures generate their sets.
"""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

ENV = "UNICORN_TEST_DATA"
IMAGE_SIZE = 32  # the evaluation fixtures' image side


@dataclass(frozen=True)
class PreparedSet:
    """A synthetic set of the fixtures: ``generate_synthetic_dataset``'s arguments, written to the set's folder
    itself or (``cache``) as ``ensure_synthetic_dataset``'s set in the folder's ``synthetic_32px``, a cache
    (``UNICORN_CACHE``) for the training tests."""

    categories: tuple[str, ...]
    mode: str
    n_models: int
    seed: int
    options: dict = field(default_factory=dict)
    cache: bool = False

    def dataset(self, out: Path) -> Path:
        """Where the dataset lies in the set's folder ``out``."""
        from unicorn.data.synthetic import synthetic_dataset_path

        if not self.cache:
            return out
        return synthetic_dataset_path(
            list(self.categories), self.mode, self.n_models, self.seed, out / "synthetic_32px"
        )

    def make(self, out: Path) -> Path:
        """Generate the set into ``out``."""
        from unicorn.data.synthetic import ensure_synthetic_dataset, generate_synthetic_dataset

        if self.cache:
            root = out / "synthetic_32px"
            ensure_synthetic_dataset(
                root, list(self.categories), self.mode, self.n_models, self.seed, progress=False, **self.options
            )
            return out
        return generate_synthetic_dataset(
            out, list(self.categories), self.mode, self.n_models, self.seed, progress=False, **self.options
        )

    def check(self, out: Path, source: Path) -> None:
        """Refuse a copy (from ``source``) that this checkout's generator would not write: another generator
        version, other settings, or no dataset where the fixtures read it."""
        from unicorn.data.synthetic.writer import StaleSyntheticDataset, check_manifest, generation_settings

        root = self.dataset(out)
        expected = generation_settings(list(self.categories), self.mode, self.n_models, self.seed, **self.options)
        try:
            if not (root / "synthetic.json").is_file():
                raise StaleSyntheticDataset(f"no synthetic.json in {root}")
            check_manifest(root, **expected)
        except StaleSyntheticDataset as err:
            raise StaleSyntheticDataset(
                f"{source} is not this checkout's set ({err}); write it again with python -m tests.support.prepared"
            ) from None


#: every generated set of the fixtures, by name
SETS: dict[str, PreparedSet] = {
    # NMR mode: 2 categories x 3 models x 6 views (also the ShapeNet-NMR fixture)
    "nmr": PreparedSet(("chair", "car"), "nmr", 3, 0, {"n_views": 6, "n_points": 600}),
    # wild mode (off-centre cameras, roll, random backgrounds)
    "wild": PreparedSet(("airplane", "lamp"), "wild", 3, 1, {"n_views": 6, "n_points": 600}),
    # NMR mode: 2 categories x 3 models x 2 views at 32 px (train split: 2 models per category)
    "eval-nmr": PreparedSet(("chair", "mug"), "nmr", 3, 0, {"image_size": IMAGE_SIZE, "n_views": 2, "n_points": 600}),
    # the 5-model chair set at 32 px that the training tests use
    "cache": PreparedSet(("chair",), "nmr", 5, 0, {"image_size": 32}, cache=True),
}


def generated(name: str, out: Path) -> Path:
    """The set ``name`` of :data:`SETS` in the folder ``out``: copied from ``$UNICORN_TEST_DATA/<name>`` where that
    holds it (and this checkout's generator would write the same), else generated.

    Raises:
        unicorn.data.synthetic.writer.StaleSyntheticDataset: the copy is another generator's or has other settings.
    """
    source = os.environ.get(ENV)
    if source and (Path(source) / name).is_dir():
        shutil.copytree(Path(source) / name, out, dirs_exist_ok=True)
        SETS[name].check(out, Path(source) / name)
        return out
    return SETS[name].make(out)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m tests.support.prepared DIR", file=sys.stderr)
        return 2
    folder = Path(args[0])
    for name, prepared in SETS.items():
        if (folder / name).exists():
            shutil.rmtree(folder / name)  # made again: from this checkout's generator
        prepared.make(folder / name)
        print(f"{folder / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
