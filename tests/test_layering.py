"""The package's floors: a module imports only from its own floor or the floors below it.

errors / caching / checks / resources / geometry -> render / metrics / data -> model -> objectives -> config -> io
-> evaluation -> lit -> cli (README, "Layout").
Checked on the source (every ``import`` / ``from`` statement, including the ones inside functions).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "unicorn"
FLOORS = [
    {"errors", "caching", "checks", "hostsync", "torch_files", "folders", "registry", "resources", "geometry"},
    {"render", "metrics", "data"},
    {"model"},
    {"objectives"},
    {"config"},
    {"io"},
    {"evaluation"},
    {"lit"},
    {"cli"},
]
FLOOR = {package: level for level, packages in enumerate(FLOORS) for package in packages}


def _imported_packages(path: Path) -> set[str]:
    """The ``unicorn.<package>`` names a source file imports."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        found.update(n.split(".")[1] for n in names if n.startswith("unicorn.") and n.count(".") >= 1)
    return found


@pytest.mark.parametrize("package", sorted(FLOOR))
def test_no_import_runs_up_a_floor(package: str) -> None:
    files = [SRC / f"{package}.py"] if (SRC / f"{package}.py").exists() else sorted((SRC / package).rglob("*.py"))
    assert files, package
    upward = {
        f"{f.relative_to(SRC)} imports unicorn.{other}"
        for f in files
        for other in _imported_packages(f)
        if other in FLOOR and FLOOR[other] > FLOOR[package]
    }
    assert not upward, sorted(upward)


def test_every_package_and_module_has_a_floor() -> None:
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    modules = {p.stem for p in SRC.glob("*.py") if p.name != "__init__.py"}
    assert packages | modules <= set(FLOOR), (packages | modules) - set(FLOOR)


def test_tests_share_code_through_tests_support_only() -> None:
    """No test module imports another test module or a conftest (shared code lives in tests/support)."""
    tests = Path(__file__).resolve().parent
    offending = []
    for path in sorted(tests.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom) or not node.module:
                continue
            module = node.module.split(".")
            if node.level == 0 and module[0] == "tests" and module[1:2] != ["support"]:
                offending.append(f"{path.relative_to(tests)} imports {node.module}")
            elif node.level > 0 and (module[-1] == "conftest" or module[-1].startswith("test_")):
                offending.append(f"{path.relative_to(tests)} imports .{node.module}")
    assert not offending, offending
