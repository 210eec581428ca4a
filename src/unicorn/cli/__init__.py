"""Command-line entry points (``unicorn-train`` and the others registered in pyproject.toml)."""
