"""ResNet-18 backbone with torchvision's parameter names (``conv1``, ``bn1``, ``layer1.0.conv1``, ...).

Written from the architecture description (He et al. 2016, torchvision's layout), without the final fc, so
that a torchvision ``resnet18`` state dict (e.g. ``resnet18-f37072fd.pth``) loads with
:meth:`ResNet18.load_torchvision_state_dict`. UNICORN trains it from scratch on raw [0, 1] 64x64 images.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["BasicBlock", "ResNet18"]


class Conv2d(nn.Conv2d):
    """``nn.Conv2d`` that skips the kernel taps falling on zero padding when the output is a single pixel.

    At 32 px, ResNet-18's last stage runs on 1 x 1 (and 2 x 2) maps, where a padded 3 x 3 convolution only ever
    multiplies its centre taps with image values: the convolution with the cropped kernel and no padding is
    the same sum (and the same weight gradient: zero on the skipped taps), and made the encoder's
    forward + backward 1.7 times faster on the CPU. Other sizes run the ordinary convolution.
    """

    def _conv_forward(self, input: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        H, W = input.shape[-2:]
        (kh, kw), (ph, pw), (sh, sw) = self.kernel_size, self.padding, self.stride
        single = (H + 2 * ph - kh) // sh == 0 and (W + 2 * pw - kw) // sw == 0
        if (
            single
            and self.padding_mode == "zeros"
            and self.groups == 1
            and self.dilation == (1, 1)
            and H + ph <= kh
            and W + pw <= kw
            and (H, W) != (kh, kw)
        ):
            # the only output pixel sees input rows 0..H-1 through taps ph..ph+H-1 (columns alike)
            return F.conv2d(input, weight[:, :, ph : ph + H, pw : pw + W], bias)
        return super()._conv_forward(input, weight, bias)


class BasicBlock(nn.Module):
    """Two 3x3 conv-BN layers with an identity (or 1x1 conv-BN ``downsample``) shortcut."""

    def __init__(self, in_channels: int, channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = Conv2d(in_channels, channels, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != channels:
            self.downsample = nn.Sequential(
                Conv2d(in_channels, channels, 1, stride=stride, bias=False), nn.BatchNorm2d(channels)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18(nn.Module):
    """ResNet-18 features: stem (7x7/2 conv, BN, ReLU, 3x3/2 max-pool), 4 stages, global average pool.

    Args:
        width: channels of the stem and the first stage, doubled at each later stage (64: ResNet-18 as
            published and as UNICORN uses it). Half the width is a quarter of the multiply-adds, but measured
            on the synthetic main job it reconstructed the colours worse and turned more views round (README,
            "Training speed"), so every preset keeps 64.

    Shapes:
        (B, 3, H, W) -> (B, 8 * width), ``out_features``. A 64x64 input gives a 2x2 map before pooling.
    """

    def __init__(self, width: int = 64) -> None:
        super().__init__()
        if width < 1:
            raise ValueError(f"encoder width must be at least 1, got {width}")
        w = int(width)
        self.out_features = 8 * w
        self.conv1 = Conv2d(3, w, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(w)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.layer1 = nn.Sequential(BasicBlock(w, w), BasicBlock(w, w))
        self.layer2 = nn.Sequential(BasicBlock(w, 2 * w, 2), BasicBlock(2 * w, 2 * w))
        self.layer3 = nn.Sequential(BasicBlock(2 * w, 4 * w, 2), BasicBlock(4 * w, 4 * w))
        self.layer4 = nn.Sequential(BasicBlock(4 * w, 8 * w, 2), BasicBlock(8 * w, 8 * w))
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"images must have shape (B, 3, H, W), got {tuple(x.shape)}")
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return self.avgpool(x).flatten(1)

    def load_torchvision_state_dict(self, state_dict: Mapping[str, torch.Tensor]) -> None:
        """Load a torchvision ``resnet18`` state dict (``fc.*`` entries dropped), strictly otherwise."""
        kept = {k: v for k, v in state_dict.items() if not k.startswith("fc.")}
        self.load_state_dict(kept, strict=True)
