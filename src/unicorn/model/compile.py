"""``torch.compile`` for the model's networks, with a fallback that says why.

The networks (the encoders, the shape field, the texture and background generators, the pose and scale heads) are
compiled in place (``nn.Module.compile``: their parameter names, hence checkpoints, stay the same); so can be other
modules a trainer names (:func:`compile_modules`: the reconstruction loss, ``Objectives.networks``). The renderer runs
eagerly (the rasterizer's packed fragments have data-dependent sizes). Where ``torch.compile`` cannot run (no C++
compiler for the CPU backend, no Triton for CUDA, an unsupported platform), :func:`compile_modules` warns once with
the reason (:class:`CompileWarning`) and leaves the modules eager: the results are the same, only slower or faster.

``model.compile`` names one of :data:`COMPILE_OPTIONS`: a ``torch.compile`` mode (inductor generates the kernels;
``reduce-overhead`` and ``max-autotune`` capture them as CUDA graphs on CUDA), or ``cudagraphs``, the backend that
captures the traced graphs as CUDA graphs of the eager kernels: no code is generated, so compiling takes the tracing
only (seconds where inductor takes minutes), and a launch-bound step still replays as a few calls; off CUDA there is
nothing to capture, and the modules stay eager (with the warning).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator

import torch
from torch import nn

from unicorn.errors import UnicornWarning
from unicorn.model.autoencoder import Unicorn

__all__ = [
    "COMPILE_MODES",
    "COMPILE_OPTIONS",
    "COMPILE_SCOPES",
    "CompileWarning",
    "compile_available",
    "compile_modules",
    "compile_options",
    "compile_networks",
    "compile_unavailable",
    "networks",
]

#: ``model.compile``'s values and the ``torch.compile`` arguments each stands for
COMPILE_OPTIONS: dict[str, dict[str, str]] = {
    "default": {"mode": "default"},
    "reduce-overhead": {"mode": "reduce-overhead"},
    "max-autotune": {"mode": "max-autotune"},
    "max-autotune-no-cudagraphs": {"mode": "max-autotune-no-cudagraphs"},
    "cudagraphs": {"backend": "cudagraphs"},
}
#: the values of ``model.compile`` (:data:`COMPILE_OPTIONS`)
COMPILE_MODES = tuple(COMPILE_OPTIONS)
#: what a trainer compiles (``model.compile_scope``): each network, or the whole forward of its steps
#: (:mod:`unicorn.lit.compiled`)
COMPILE_SCOPES = ("networks", "step")


class CompileWarning(UnicornWarning):
    """``torch.compile`` cannot run here: the networks run eagerly (the message says why)."""


def compile_options(mode: str) -> dict[str, str]:
    """The ``torch.compile`` arguments of ``model.compile=mode`` (:data:`COMPILE_OPTIONS`).

    Raises:
        ValueError: ``mode`` is not one of :data:`COMPILE_MODES`.
    """
    if mode not in COMPILE_OPTIONS:
        raise ValueError(f"the compile mode must be one of {COMPILE_MODES}, got {mode!r}")
    return dict(COMPILE_OPTIONS[mode])


def networks(model: Unicorn) -> Iterator[tuple[str, nn.Module]]:
    """The model's learned networks by attribute name (``encoders.0``, ``shape``, ``texture``, ``background``,
    ``pose``, ``scale``); a model without a background has none."""
    for i, encoder in enumerate(model.encoders):
        yield f"encoders.{i}", encoder
    for name in ("shape", "texture", "background", "pose", "scale"):
        module = getattr(model, name)
        if module is not None:
            yield name, module


def compile_unavailable(device: torch.device | str, mode: str = "default") -> str | None:
    """None where ``torch.compile`` compiles and runs a small function on ``device`` as ``model.compile=mode`` does;
    otherwise why not, in one line (the exception's type and first line)."""
    options = compile_options(mode)
    if options.get("backend") == "cudagraphs" and torch.device(device).type != "cuda":
        return "the cudagraphs backend captures CUDA graphs: it needs a CUDA device"

    def probe(x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x * 2.0 + 1.0)

    try:
        probe_compiled = torch.compile(probe, dynamic=False, **options)
        probe_compiled(torch.ones(4, device=device))
    except Exception as error:  # any failure of the toolchain means: run eagerly
        first = str(error).strip().splitlines()[0] if str(error).strip() else ""
        return f"{type(error).__name__}: {first}"[:300]
    return None


def compile_available(device: torch.device | str, what: str, stacklevel: int = 1, mode: str = "default") -> bool:
    """Whether ``torch.compile`` can run on ``device`` in ``mode`` (:func:`compile_unavailable`); where it cannot,
    one :class:`CompileWarning` names the reason and says that ``what`` runs eagerly (``stacklevel`` as for
    :func:`warnings.warn`, counted from the caller)."""
    reason = compile_unavailable(device, mode)
    if reason is not None:
        warnings.warn(
            f"torch.compile cannot run on {device} ({reason}): {what} run eagerly",
            CompileWarning,
            stacklevel=stacklevel + 1,
        )
    return reason is None


def compile_modules(modules: Iterable[nn.Module], mode: str = "default", device: torch.device | str = "cpu") -> bool:
    """Compile modules in place (``nn.Module.compile`` with ``mode``'s :data:`COMPILE_OPTIONS`; each compiles at
    its first call).

    Where ``torch.compile`` cannot run on ``device`` (:func:`compile_unavailable`), nothing is compiled and one
    :class:`CompileWarning` names the reason.

    Returns:
        Whether the modules were compiled.

    Raises:
        ValueError: ``mode`` is not one of :data:`COMPILE_MODES`.
    """
    options = compile_options(mode)
    if not compile_available(device, "the networks", stacklevel=2, mode=mode):
        return False
    for module in modules:
        module.compile(**options)
    return True


def compile_networks(model: Unicorn, mode: str = "default", device: torch.device | str | None = None) -> bool:
    """Compile the model's networks in place (:func:`networks`; :func:`compile_modules`), on ``device`` (the
    model's by default).

    Returns:
        Whether the networks were compiled.

    Raises:
        ValueError: ``mode`` is not one of :data:`COMPILE_MODES`.
    """
    device = model.template.verts.device if device is None else device
    return compile_modules([module for _, module in networks(model)], mode, device)
