"""Developer sessions: ``nox -s tests``, ``nox -s train``, ``nox -s lint``, ``nox -s docs``, ``nox -s bench``,
``nox -s quality``, ``nox -s package``, ``nox -s lowest``.

Every session that runs unicorn's code reuses its virtual environment and installs torch only when the
environment has none, so torch is never reinstalled and a CPU machine never pulls the CUDA build by accident:

- ``UNICORN_TORCH`` (default ``torch==2.13.0``, the version the project is tested with) is what gets installed;
- ``UNICORN_TORCH_INDEX`` optionally names the index to take it from, e.g. ``https://download.pytorch.org/whl/cpu``
  on a CPU-only Linux machine where PyPI's default torch wheel would bring several GB of CUDA libraries.
"""

from __future__ import annotations

import ctypes.util
import os
import re
import shutil

import nox

nox.needs_version = ">=2024.3.2"
nox.options.sessions = ["lint", "tests"]
nox.options.reuse_venv = "yes"

PYTHON = os.environ.get("UNICORN_PYTHON", "3.11")


def install_torch(session: nox.Session) -> None:
    """Install torch into the session's environment unless it already has one."""
    probe = "import importlib.util as u; print('HAS_TORCH' if u.find_spec('torch') else 'NO_TORCH')"
    if "HAS_TORCH" in str(session.run("python", "-c", probe, silent=True, log=False)):
        return
    spec = os.environ.get("UNICORN_TORCH", "torch==2.13.0")
    index = os.environ.get("UNICORN_TORCH_INDEX")
    session.install(spec, *(["--index-url", index] if index else []))


def ensure_libusb(session: nox.Session) -> None:
    """open3d needs the system's libusb-1.0; install Debian's package when we can, else say what is missing."""
    if ctypes.util.find_library("usb-1.0"):
        return
    if shutil.which("apt-get") and os.geteuid() == 0:
        session.log("installing Debian's libusb-1.0-0 (needed by open3d)")
        session.run("apt-get", "update", "-qq", external=True)
        session.run("apt-get", "install", "-y", "-qq", "libusb-1.0-0", external=True)
        return
    session.error(
        "open3d needs the system library libusb-1.0: install it (Debian/Ubuntu: apt-get install libusb-1.0-0)"
    )


def install_project(session: nox.Session, *extras: str) -> None:
    ensure_libusb(session)
    install_torch(session)
    target = f".[{','.join(extras)}]" if extras else "."
    session.install("-e", target)


def parallel_workers() -> list[str]:
    """pytest-xdist's options: one worker per core, at most 8 (each holds torch and its fixtures in memory; most of
    the suite's time is single-threaded, in the commands it starts). ``UNICORN_TEST_WORKERS=0`` runs in one process.
    """
    workers = int(os.environ.get("UNICORN_TEST_WORKERS", min(os.cpu_count() or 1, 8)))
    return ["-n", str(workers), "--dist", "worksteal"] if workers > 1 else []


@nox.session(python=PYTHON)
def tests(session: nox.Session) -> None:
    """The test suite (CPU; tests marked gpu run only where CUDA is present). Extra arguments go to pytest."""
    install_project(session, "dev")
    run_pytest(session)


def run_pytest(session: nox.Session) -> None:
    """pytest with the session's arguments (default: quiet, :func:`parallel_workers`), after ``npm ci`` where
    Node.js is present (the glTF validator of the GLB test)."""
    if shutil.which("npm") and not os.path.isdir("node_modules/gltf-validator"):
        session.run("npm", "ci", "--no-audit", "--no-fund", external=True)
    session.run("pytest", *(session.posargs or ["-q", *parallel_workers()]))


def lowest_requirements(pyproject: str = "pyproject.toml", extras: tuple[str, ...] = ("dev",)) -> list[str]:
    """The dependencies ``pyproject`` declares (and those of ``extras``) pinned at their declared minimums:
    ``hydra-core>=1.3,<1.4`` gives ``hydra-core==1.3``; torch is left out (:func:`install_torch` installs it)."""
    import tomllib  # Python 3.11+; here, not at the top, so that nox under 3.10 runs the other sessions

    with open(pyproject, "rb") as f:
        project = tomllib.load(f)["project"]
    declared = project["dependencies"] + [r for e in extras for r in project["optional-dependencies"][e]]
    pins = []
    for requirement in declared:
        match = re.match(r"^\s*([A-Za-z0-9_.-]+)\s*>=\s*([^,;\s]+)", requirement)
        if match is None:
            raise ValueError(f"pyproject.toml: {requirement!r} declares no minimum version (name>=X)")
        if match[1].lower() != "torch":
            pins.append(f"{match[1]}=={match[2]}")
    return sorted(set(pins))


@nox.session(python=PYTHON)
def lowest(session: nox.Session) -> None:
    """The test suite with every dependency at the minimum pyproject.toml declares (torch as in the other sessions:
    ``UNICORN_TORCH``). Extra arguments go to pytest."""
    ensure_libusb(session)
    install_torch(session)
    probe = "import importlib.metadata as m; print(m.version('torch'))"  # without importing torch: no warnings
    torch_version = str(session.run("python", "-c", probe, silent=True, log=False)).split()[-1]
    constraints = os.path.join(session.create_tmp(), "torch.txt")
    with open(constraints, "w", encoding="utf-8") as f:
        f.write(f"torch=={torch_version}\n")  # a pin that asks for another torch fails instead of replacing it
    session.install("-c", constraints, *lowest_requirements())
    session.install("--no-deps", "-e", ".")
    session.run("python", "-m", "pip", "check")
    run_pytest(session)


@nox.session(python=PYTHON)
def train(session: nox.Session) -> None:
    """The main job: train on the offline synthetic default. Extra arguments are Hydra overrides."""
    install_project(session)
    session.run("unicorn-train", "experiment=synthetic", *session.posargs)


@nox.session(python=PYTHON)
def lint(session: nox.Session) -> None:
    """ruff's rules and its formatting on the package, tests, benchmarks, experiments, the docs site's extension and
    this file."""
    session.install("ruff>=0.5")
    paths = ("src", "tests", "benchmarks", "experiments", "docs/_ext", "noxfile.py")
    session.run("ruff", "check", *paths)
    session.run("ruff", "format", "--check", *paths)


@nox.session(python=PYTHON)
def docs(session: nox.Session) -> None:
    """The documentation site (MkDocs, Material theme), built with ``--strict``: a broken link or reference fails.

    The API pages are read from the source by static analysis (griffe), so this environment has no torch and does
    not install unicorn. Extra arguments go to ``mkdocs build`` (e.g. ``-- --site-dir site``).
    """
    session.install("mkdocs>=1.6", "mkdocs-material>=9.5", "mkdocstrings[python]>=0.29", "mkdocstrings-python>=1.16")
    site = os.path.join(session.create_tmp(), "site")  # a later --site-dir in the arguments wins
    session.run("mkdocs", "build", "--strict", "--site-dir", site, *session.posargs)


@nox.session(python=PYTHON)
def bench(session: nox.Session) -> None:
    """Benchmarks (pass e.g. ``-- --device cuda`` or ``-- --quick``)."""
    install_project(session, "dev")
    session.run("python", "benchmarks/bm_render.py", *session.posargs)


@nox.session(python=PYTHON)
def quality(session: nox.Session) -> None:
    """The quality benchmark: default experiment, ablations, wild mode and baselines (about 50 min on 2 CPU cores)."""
    install_project(session, "dev")
    session.run("python", "benchmarks/quality.py", *session.posargs)


@nox.session(python=PYTHON, reuse_venv=False)
def package(session: nox.Session) -> None:
    """Build the wheel, install it non-editable in a fresh environment and check the configs shipped in it."""
    ensure_libusb(session)
    install_torch(session)
    session.install("build")
    tmp = session.create_tmp()
    session.run("python", "-m", "build", "--wheel", "--outdir", tmp)
    wheels = [f for f in os.listdir(tmp) if f.endswith(".whl")]
    session.install(os.path.join(tmp, wheels[0]))
    session.chdir(tmp)
    session.run(
        "python", "-c",
        "import importlib.resources as r, unicorn; "
        "assert (r.files('unicorn') / 'conf' / 'renderer' / 'layered.yaml').is_file(), 'configs missing from wheel'",
    )  # fmt: skip
