"""Offline synthetic benchmark: procedural objects, an independent ray-casting renderer, a DVR/NMR writer."""

from unicorn.data.synthetic.shapes import CATEGORIES, build_object
from unicorn.data.synthetic.writer import (
    default_cache_dir,
    ensure_synthetic_dataset,
    generate_synthetic_dataset,
    synthetic_dataset_path,
)

__all__ = [
    "CATEGORIES",
    "build_object",
    "default_cache_dir",
    "ensure_synthetic_dataset",
    "generate_synthetic_dataset",
    "synthetic_dataset_path",
]
