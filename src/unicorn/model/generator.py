"""Texture and background generators: a code regressor and a GIRAFFE-style upsampling decoder."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from unicorn.checks import check_shape
from unicorn.geometry.mesh import mirror_spherical_map
from unicorn.model.filtering import separable_filter
from unicorn.model.mlp import MLP
from unicorn.model.progressive import ProgressiveMask

__all__ = ["Blur", "CodeGenerator", "GiraffeGenerator", "mean_texture"]


def _upsampled(x: torch.Tensor, mode: str) -> torch.Tensor:
    """(B, C, H, W) -> (B, C, 2H, 2W), nearest or bilinear (``align_corners=False``).

    Under ``torch.compile`` a 1 x 1 map is doubled by a broadcast instead, the same values: the interpolations'
    backward is a scatter for which the CPU backend fails to generate code from a 1 x 1 input
    (pytorch/pytorch#160391). Eager runs keep the interpolation and its gradients to the last bit."""
    if x.shape[-2:] == (1, 1) and torch.compiler.is_compiling():
        return x.expand(-1, -1, 2, 2)
    return F.interpolate(x, scale_factor=2.0, mode=mode, align_corners=False if mode == "bilinear" else None)


class Blur(nn.Module):
    """Depthwise ``[1, 2, 1] x [1, 2, 1] / 16`` blur with reflect padding (anti-aliases upsampling).

    As a separable filter (:func:`unicorn.model.filtering.separable_filter`): the same values as the depthwise
    convolution, without oneDNN's slow path for 3-channel depthwise convolutions.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H, W); H and W must be >= 2 for reflect padding."""
        taps = [0.25, 0.5, 0.25]
        return separable_filter(x, taps, taps, "reflect")


class GiraffeGenerator(nn.Module):
    """Code (B, C) -> image (B, 3, S, S) in [0, 1], as GIRAFFE's neural renderer without its feature input.

    Starting from the code as a 1x1 feature map, each of ``log2(S)`` blocks nearest-upsamples the features
    and applies a 3x3 conv + ReLU; an RGB skip branch adds a 3x3 conv projection of every block's features
    to a running RGB image that is bilinearly upsampled and blurred between blocks. Channels halve at every
    block down to ``min_features``. No biases and no normalisation, so a zero code gives a 0.5-grey image.

    Args:
        code_dim: code size C (also the input channel count).
        img_size: output side S, a power of 2 (64).
        min_features: smallest feature width (16 small, 64 big).
    """

    def __init__(self, code_dim: int, img_size: int = 64, min_features: int = 16) -> None:
        super().__init__()
        n_blocks = int(round(math.log2(img_size)))
        if img_size < 2 or 2**n_blocks != img_size:
            raise ValueError(f"img_size must be a power of 2 >= 2, got {img_size}")
        if code_dim < 1:
            raise ValueError(f"code_dim must be >= 1, got {code_dim}")
        self.code_dim, self.img_size, self.min_features = code_dim, img_size, min_features

        def nch(i: int) -> int:
            return max(code_dim // 2**i, min_features)

        self.conv_layers = nn.ModuleList(
            [nn.Conv2d(code_dim, nch(1), 3, padding=1, bias=False)]
            + [nn.Conv2d(nch(i + 1), nch(i + 2), 3, padding=1, bias=False) for i in range(n_blocks - 1)]
        )
        self.conv_rgb = nn.ModuleList(
            [nn.Conv2d(code_dim, 3, 3, padding=1, bias=False)]
            + [nn.Conv2d(nch(i + 1), 3, 3, padding=1, bias=False) for i in range(n_blocks)]
        )
        # index 1 is the blur, as in the reference's `upsample_rgb.1`
        self.upsample_rgb = nn.Sequential(nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False), Blur())
        for conv in [*self.conv_layers, *self.conv_rgb]:
            nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")

    def _upsample_rgb(self, rgb: torch.Tensor) -> torch.Tensor:
        """``upsample_rgb``: bilinear doubling (:func:`_upsampled`), then the blur."""
        return self.upsample_rgb[1](_upsampled(rgb, "bilinear"))

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """(B, C) -> (B, 3, S, S) in [0, 1]."""
        check_shape(code, "B, C", "code", {"C": self.code_dim})
        net = code[:, :, None, None]
        rgb = self._upsample_rgb(self.conv_rgb[0](net))
        last = len(self.conv_layers) - 1
        for i, conv in enumerate(self.conv_layers):
            net = torch.relu(conv(_upsampled(net, "nearest")))
            rgb = rgb + self.conv_rgb[i + 1](net)
            if i < last:
                rgb = self._upsample_rgb(rgb)
        return torch.sigmoid(rgb)


class CodeGenerator(nn.Module):
    """Image features -> masked code -> generated image (texture UV map or background).

    Names follow the reference's ``ProgressiveGenerator`` (``regressor``, ``generator.conv_layers``,
    ``generator.conv_rgb``).

    Args:
        in_features: encoder feature size (512).
        code_dim: full code size (texture 128 / 512, background 128 / 256).
        img_size: output side (64).
        min_features: generator's smallest width (16 small, 64 big).
        n_reg_units, n_reg_layers: code regressor width and depth (zero-initialised last layer).
        active_dims: initial active code size.
        symmetric: a texture map mirror-symmetric through the template's plane z = 0 (the mean of the generated
            map and its mirror, :func:`unicorn.geometry.mesh.mirror_spherical_map`; needs the seamless spherical
            UVs); the paper uses no symmetry prior (False).
    """

    def __init__(
        self,
        in_features: int = 512,
        code_dim: int = 128,
        img_size: int = 64,
        min_features: int = 16,
        n_reg_units: int = 128,
        n_reg_layers: int = 3,
        active_dims: int | None = None,
        symmetric: bool = False,
    ) -> None:
        super().__init__()
        self.symmetric = symmetric
        self.regressor = MLP(in_features, code_dim, n_reg_units, n_reg_layers, zero_last=True)
        self.mask = ProgressiveMask(code_dim, active_dims)
        self.generator = GiraffeGenerator(code_dim, img_size, min_features)

    @property
    def code_dim(self) -> int:
        return self.mask.code_dim

    def code(self, features: torch.Tensor) -> torch.Tensor:
        """(B, in_features) -> masked code (B, code_dim)."""
        return self.mask(self.regressor(features))

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """Masked code (B, code_dim) -> image (B, 3, S, S) in [0, 1]."""
        image = self.generator(code)
        return (image + mirror_spherical_map(image)) / 2 if self.symmetric else image


def mean_texture(maps: torch.Tensor) -> torch.Tensor:
    """Replace every texture image by its mean colour: (B, C, H, W) -> (B, C, H, W)."""
    return maps.mean(dim=(2, 3), keepdim=True).expand_as(maps)
