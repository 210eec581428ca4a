"""Perceptual reconstruction losses, per sample.

- :class:`VGGPerceptualLoss`: the paper's loss, an L2 distance between channel-normalised VGG16
  ``relu3_3`` features of ImageNet-normalised images, with torchvision's ImageNet VGG16 weights
  (``VGG16_Weights.IMAGENET1K_V1``: ``vgg16-397923af.pth``). The weights are found as torchvision finds them:
  in torch's hub cache (``<torch.hub.get_dir()>/checkpoints``, ``$TORCH_HOME``), downloaded there with the
  hash checked when absent; an offline machine names a copy of the file instead (``paths.vgg16`` /
  ``$UNICORN_VGG16``). The network up to ``relu3_3`` is defined here, with torchvision's parameter names
  (``features.0.weight``, ... ``features.14.bias``), rather than imported from torchvision: PyPI's Linux
  torchvision wheels are CUDA builds that cannot be imported next to a CPU-only torch. Cost: at 64x64 it is
  roughly ten times a ResNet-18 forward, and the pose step applies it to K x B renders.
- :class:`StructuralLoss`: a cheap weights-free stand-in for machines without the VGG16 file: multi-scale
  SSIM dissimilarity plus an L1 distance between Sobel image gradients (kornia's definitions), both averaged over three
  scales (1, 1/2, 1/4). It is not a calibrated replacement: it rewards matching local structure and edges
  (what makes textures informative for the pose) but its magnitude differs from the VGG loss, so its weight
  (``perceptual_weight``) may need retuning; a weight of 1 keeps it of the order of the pixel MSE * 10.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from unicorn.caching import cache_outside_compile
from unicorn.checks import check_shape
from unicorn.errors import UserError
from unicorn.model.config import LOSS_KEYS
from unicorn.model.filtering import separable_filter
from unicorn.registry import Registry
from unicorn.torch_files import TorchFileError, read_plain

__all__ = [
    "VGG16_FILE",
    "VGG16_URL",
    "StructuralLoss",
    "VGG16Relu33",
    "VGGPerceptualLoss",
    "VGGWeightsError",
    "VGGWeightsNotFoundError",
    "build_perceptual",
    "list_perceptual_losses",
    "load_vgg16_weights",
    "register_perceptual",
    "sobel_gradient",
    "ssim_map",
    "vgg16_cache_path",
]

#: torchvision's ``VGG16_Weights.IMAGENET1K_V1``; the file name ends with the first digits of its SHA-256
VGG16_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"
VGG16_FILE = "vgg16-397923af.pth"
#: what a user can do about missing weights (one line, shared by every message)
_VGG16_OPTIONS = (
    f"on an offline machine copy torchvision's {VGG16_FILE} ({VGG16_URL}) here and pass paths.vgg16=FILE "
    "(or set UNICORN_VGG16=FILE), or put it in {cache}; or train with the weights-free loss: "
    "model.loss.perceptual=structural"
)
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
# torchvision's VGG16 "D" configuration up to relu3_3: (index of the conv in `features`, in, out)
_CONVS = (
    (0, 3, 64),
    (2, 64, 64),
    (5, 64, 128),
    (7, 128, 128),
    (10, 128, 256),
    (12, 256, 256),
    (14, 256, 256),
)
_POOLS = (4, 9)


def _check_pair(rec: torch.Tensor, target: torch.Tensor) -> None:
    dims = check_shape(rec, "B, 3, H, W", "rec")
    check_shape(target, "B, 3, H, W", "target", dims)


class VGGWeightsNotFoundError(UserError, FileNotFoundError):
    """The perceptual loss's VGG16 weights are neither where the user said nor in (nor downloadable to) the cache."""


class VGGWeightsError(UserError, ValueError):
    """The file given for the VGG16 weights cannot be read, or is not torchvision's VGG16 state dict."""


def vgg16_cache_path() -> Path:
    """Where torch's hub (and torchvision) keeps the VGG16 file: ``<torch.hub.get_dir()>/checkpoints/<file>``."""
    return Path(torch.hub.get_dir()) / "checkpoints" / VGG16_FILE


def load_vgg16_weights(path: str | os.PathLike | None, download: bool = True) -> dict[str, torch.Tensor]:
    """torchvision's ImageNet VGG16 state dict, from ``path`` or from torch's hub cache.

    Args:
        path: a copy of ``vgg16-397923af.pth`` (any file name); None: torch's hub cache, where the file is
            downloaded (SHA-256 prefix checked, as torchvision does) when absent and ``download`` is True.
        download: allow the download.

    Raises:
        VGGWeightsNotFoundError: the file is missing and cannot be downloaded; the one-line message says what to
            pass (``paths.vgg16`` / ``UNICORN_VGG16``), where the cache is, and the weights-free alternative.
        VGGWeightsError: the file cannot be read (not a ``torch.save`` file, or one that would inflate in memory).
    """
    cache = vgg16_cache_path()
    if path is not None:
        path = Path(os.fspath(path)).expanduser()
        if not path.is_file():
            options = _VGG16_OPTIONS.format(cache=cache.parent)
            raise VGGWeightsNotFoundError(f"VGG16 weights for the perceptual loss not found at {path}: {options}")
        state = _read_weights(path)
    elif cache.is_file():  # torch's hub would load it unchecked: its hash is checked only when it downloads
        state = _read_weights(cache)
    elif download:
        try:
            state = torch.hub.load_state_dict_from_url(
                VGG16_URL, map_location="cpu", progress=False, check_hash=True, weights_only=True
            )
        except OSError as err:  # URLError and socket errors are OSErrors
            reason = getattr(err, "reason", None) or err
            options = _VGG16_OPTIONS.format(cache=cache.parent)
            raise VGGWeightsNotFoundError(
                f"VGG16 weights for the perceptual loss: {VGG16_FILE} is not in torch's cache and could not be "
                f"downloaded ({reason}); {options}"
            ) from None
    else:
        options = _VGG16_OPTIONS.format(cache=cache.parent)
        raise VGGWeightsNotFoundError(f"VGG16 weights for the perceptual loss: no {cache}; {options}")
    if isinstance(state, Mapping) and "state_dict" in state:
        state = state["state_dict"]
    if not isinstance(state, Mapping):
        raise VGGWeightsError(f"the VGG16 weights {path or cache} hold {type(state).__name__}, not a state dict")
    return dict(state)


def _read_weights(path: Path) -> Any:
    """A weights file (:func:`~unicorn.torch_files.read_plain`)."""
    try:
        return read_plain(path)
    except TorchFileError as err:
        raise VGGWeightsError(f"cannot read the VGG16 weights {path}: {err}") from None


class VGG16Relu33(nn.Module):
    """VGG16 ``features[:16]`` (conv1_1 ... relu3_3), frozen: (B, 3, H, W) -> (B, 256, H/4, W/4)."""

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        convs = {i: (cin, cout) for i, cin, cout in _CONVS}
        for i in range(16):
            if i in convs:
                layers.append(nn.Conv2d(*convs[i], kernel_size=3, padding=1))
            elif i in _POOLS:
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers.append(nn.ReLU())
        self.features = nn.Sequential(*layers)
        # frozen ImageNet weights: non-persistent buffers, so they follow .to(device) but are neither
        # optimised (not in .parameters()) nor saved in the model's state dict (they come from the file)
        for i, _, _ in _CONVS:
            conv = self.features[i]
            for name in ("weight", "bias"):
                value = getattr(conv, name).detach()
                delattr(conv, name)
                conv.register_buffer(name, value, persistent=False)

    def load_torchvision_state_dict(self, state_dict: Mapping[str, torch.Tensor]) -> None:
        """Copy the ``features.N.weight`` / ``.bias`` entries (N < 16) of a torchvision VGG16 state dict.

        Raises:
            VGGWeightsError: an expected entry is missing, or is not a tensor of its shape.
        """
        for i, _, _ in _CONVS:
            conv = self.features[i]
            for name in ("weight", "bias"):
                key = f"features.{i}.{name}"
                if key not in state_dict:
                    raise VGGWeightsError(f"VGG16 state dict lacks '{key}' (is it torchvision's vgg16?)")
                value = state_dict[key]
                target = getattr(conv, name)
                if not isinstance(value, torch.Tensor) or tuple(value.shape) != tuple(target.shape):
                    got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
                    raise VGGWeightsError(f"VGG16 state dict: '{key}' is {got}, expected shape {tuple(target.shape)}")
                with torch.no_grad():
                    target.copy_(value)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)


class VGGPerceptualLoss(nn.Module):
    """Per-sample ``mean_{c,h,w} (phi(rec) - phi(target))^2``, phi: channel-normalised relu3_3 features.

    Inputs are [0, 1] images, ImageNet-normalised here; no resizing (64x64 gives 16x16x256 features).
    The VGG weights are frozen non-persistent buffers (not trained, not saved with the model); gradients
    still flow to the inputs.

    Args:
        weights: path of a copy of torchvision's ``vgg16-397923af.pth``; None: torch's hub cache, downloading
            the file there when absent (see :func:`load_vgg16_weights`); or an already loaded state dict with
            torchvision names (e.g. taken from a released UNICORN checkpoint).

    Raises:
        VGGWeightsNotFoundError: no weights (the one-line message says what to pass).
        VGGWeightsError: the weights cannot be read or are not torchvision's VGG16.
    """

    mean: torch.Tensor
    std: torch.Tensor

    def __init__(self, weights: str | os.PathLike | Mapping[str, torch.Tensor] | None) -> None:
        super().__init__()
        state = weights if isinstance(weights, Mapping) else load_vgg16_weights(weights)
        self.vgg = VGG16Relu33()
        try:
            self.vgg.load_torchvision_state_dict(state)
        except VGGWeightsError as err:
            if isinstance(weights, Mapping):
                raise
            raise VGGWeightsError(f"the VGG16 weights {weights or vgg16_cache_path()}: {err}") from None
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, rec: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) x 2 -> (B,)."""
        _check_pair(rec, target)
        B = rec.shape[0]
        # one pass over both images (the BN-free VGG makes this identical to two passes)
        feats = self.vgg((torch.cat([rec, target]) - self.mean) / self.std)
        feats = feats / (feats.norm(dim=1, keepdim=True) + 1e-10)
        return (feats[:B] - feats[B:]).pow(2).flatten(1).mean(1)


@cache_outside_compile(maxsize=None)
def _gaussian_taps(window_size: int, sigma: float = 1.5) -> tuple[float, ...]:
    """Normalised 1-D Gaussian taps (kornia's SSIM window: sigma 1.5 whatever the size), computed once per size (in
    Python floats: ``torch.compile`` traces it without reading a tensor back)."""
    g = [math.exp(-((i - window_size // 2) ** 2) / (2 * sigma**2)) for i in range(window_size)]
    return tuple(v / math.fsum(g) for v in g)


def ssim_map(x: torch.Tensor, y: torch.Tensor, window_size: int = 5, max_val: float = 1.0) -> torch.Tensor:
    """SSIM index map of two (B, C, H, W) images, as ``kornia.metrics.ssim(x, y, window_size, max_val)``.

    Same definition (Gaussian window sigma 1.5, reflect padding, c1 = (0.01 L)^2, c2 = (0.03 L)^2, eps 1e-12),
    computed with one separable filtering pass over the five stacked moments. Returns (B, C, H, W).
    """
    C = x.shape[1]
    moments = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    taps = _gaussian_taps(window_size)
    f = separable_filter(moments, taps, taps, "reflect")
    mu_x, mu_y, xx, yy, xy = f.split(C, dim=1)
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    num = (2 * mu_xy + c1) * (2 * (xy - mu_xy) + c2)
    den = (mu_xx + mu_yy + c1) * ((xx - mu_xx) + (yy - mu_yy) + c2)
    return num / (den + 1e-12)


def sobel_gradient(x: torch.Tensor) -> torch.Tensor:
    """Normalised Sobel derivatives (B, C, 2, H, W) with replicated border, as ``kornia.filters.spatial_gradient``."""
    smooth, diff = [0.25, 0.5, 0.25], [-0.5, 0.0, 0.5]
    dx = separable_filter(x, smooth, diff, "replicate")
    dy = separable_filter(x, diff, smooth, "replicate")
    return torch.stack([dx, dy], dim=2)


class StructuralLoss(nn.Module):
    """Weights-free per-sample loss: ``mean_s [(1 - SSIM_s) / 2 + |grad_s(rec) - grad_s(target)|]``.

    SSIM and the Sobel gradients are kornia's definitions (``kornia.metrics.ssim``,
    ``kornia.filters.spatial_gradient``; the tests compare with them), computed by :func:`ssim_map` and
    :func:`sobel_gradient` as small matrix products because kornia's depthwise convolutions dominated the CPU
    training step. The gradient is linear, so ``grad(rec) - grad(target)`` is computed as ``grad(rec - target)``.

    Args:
        n_scales: number of scales (each halves the resolution with 2x2 average pooling).
        window_size: SSIM Gaussian window (odd).
    """

    def __init__(self, n_scales: int = 3, window_size: int = 5) -> None:
        super().__init__()
        if n_scales < 1 or window_size % 2 == 0:
            raise ValueError(f"need n_scales >= 1 and an odd window, got {n_scales}, {window_size}")
        self.n_scales, self.window_size = n_scales, window_size

    def forward(self, rec: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) x 2 -> (B,)."""
        _check_pair(rec, target)
        total = rec.new_zeros(rec.shape[0])
        for s in range(self.n_scales):
            if s > 0:
                rec, target = F.avg_pool2d(rec, 2), F.avg_pool2d(target, 2)
            window = min(self.window_size, 2 * (min(rec.shape[-2:]) // 2) - 1)
            ssim = ssim_map(rec, target, max(window, 1), max_val=1.0)
            grad = sobel_gradient(rec - target)
            total = total + ((1 - ssim) / 2).flatten(1).mean(1) + grad.abs().flatten(1).mean(1)
        return total / self.n_scales


# ---------------------------------------------------------------------------------------------- registry
_PERCEPTUAL_LOSSES: Registry[nn.Module] = Registry("perceptual loss")


def register_perceptual(
    name: str, *, overwrite: bool = False
) -> Callable[[Callable[..., nn.Module]], Callable[..., nn.Module]]:
    """Decorator: make a perceptual-loss constructor available as ``loss.perceptual=name``.

    The constructor receives the loss group's options it names (e.g. ``vgg_weights``) as keywords.
    """
    return _PERCEPTUAL_LOSSES.register(name, overwrite=overwrite)


def list_perceptual_losses() -> list[str]:
    """The registered perceptual-loss names, sorted."""
    return _PERCEPTUAL_LOSSES.names()


def build_perceptual(name: str | None, **options: object) -> nn.Module | None:
    """The perceptual loss registered as ``name`` (None: no perceptual loss), from the options its constructor names;
    the other keys of the ``loss`` group (:data:`~unicorn.model.config.LOSS_KEYS`) are left out.

    Raises:
        unicorn.registry.UnknownNameError: an unknown name (the known ones listed).
        unicorn.registry.UnknownOptionError: an option that is neither the constructor's nor a ``loss`` key.
        VGGWeightsNotFoundError: ``"vgg"`` without weights.
    """
    return None if name is None else _PERCEPTUAL_LOSSES.build(name, options, group_keys=LOSS_KEYS)


@register_perceptual("vgg")
def _vgg(vgg_weights: str | os.PathLike | None = None) -> nn.Module:
    return VGGPerceptualLoss(vgg_weights)


@register_perceptual("structural")
def _structural() -> nn.Module:
    return StructuralLoss()
