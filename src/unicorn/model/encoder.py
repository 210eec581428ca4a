"""ResNet-18 backbone with torchvision's parameter names (``conv1``, ``bn1``, ``layer1.0.conv1``, ...).

Written from the architecture description (He et al. 2016, torchvision's layout), without the final fc, so
that a torchvision ``resnet18`` state dict (e.g. ``resnet18-f37072fd.pth``) loads with
:meth:`ResNet18.load_torchvision_state_dict`. UNICORN trains it from scratch on raw [0, 1] 64x64 images.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from unicorn.checks import check_shape

__all__ = ["STAGES", "BasicBlock", "Conv2d", "ResNet18", "crop_optimizer_state"]

#: ResNet-18's four stages, in network order; stage ``i`` (from 0) has ``width * 2**i`` channels
STAGES = ("layer1", "layer2", "layer3", "layer4")


def distinct_stages(names: Sequence[str]) -> bool:
    """Whether ``names`` are one or more distinct names of :data:`STAGES`."""
    return bool(names) and len(set(names)) == len(names) and all(name in STAGES for name in names)


class Conv2d(nn.Conv2d):
    """``nn.Conv2d`` that can train only the kernel taps which meet image values at one input size.

    At 32 px, ResNet-18's last stage runs on 2 x 2 and 1 x 1 maps: the single output pixel of a padded 3 x 3
    convolution multiplies only the centre taps with image values, and the outer taps, which meet zero padding,
    never receive a gradient. After :meth:`keep_taps_for`, ``weight`` holds only the taps that meet the image
    (at that size the convolution with it and no padding is the same sum), and the rest of the kernel is kept,
    untrained, beside it: :meth:`full_weight` and the state dict give the whole kernel (ResNet-18's shapes;
    a full kernel loads back into both parts), and inputs of any other size run the ordinary convolution with
    it. Training the full kernels instead means zero-filling, copying and updating (Adam) 512 x 512 x 3 x 3
    gradients that are 8/9 zero (the cost: ``docs/performance.md``, "What keeps training fast on a CPU").
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.taps: tuple[int, int, int, int] | None = None  # (top, left, height, width) of the trained taps
        # the untrained rest of the kernel, (out, in, kh, kw); a plain attribute, not a buffer, so that DDP does
        # not broadcast it at every forward (moved with the module by _apply)
        self.kernel: torch.Tensor | None = None
        self.register_state_dict_post_hook(_save_full_kernel)
        self.register_load_state_dict_pre_hook(_load_full_kernel)

    def keep_taps_for(self, height: int, width: int) -> bool:
        """Train only the taps that meet image values when the input is ``height`` x ``width``.

        Applies when the output is a single pixel whose window reaches into the zero padding; returns whether
        it did. Call it before an optimizer takes the parameters (``weight`` becomes a new, smaller parameter).
        """
        (kh, kw), (ph, pw), (sh, sw) = self.kernel_size, self.padding, self.stride
        single = (height + 2 * ph - kh) // sh == 0 and (width + 2 * pw - kw) // sw == 0
        if not (
            single
            and self.padding_mode == "zeros"
            and self.groups == 1
            and self.dilation == (1, 1)
            and height + ph <= kh
            and width + pw <= kw
            and (height, width) != (kh, kw)
        ):
            return False
        if self.taps is not None:
            raise RuntimeError("keep_taps_for was already applied to this convolution")
        # the only output pixel sees input rows 0..height-1 through taps ph..ph+height-1 (columns alike)
        full = self.weight.detach()
        self.kernel = full.clone()
        self.taps = (ph, pw, height, width)
        self.weight = nn.Parameter(full[self.window].clone(), self.weight.requires_grad)
        return True

    @property
    def window(self) -> tuple[slice, ...]:
        """Index of the trained taps in a whole kernel (out, in, kh, kw), from :attr:`taps`."""
        top, left, h, w = self.taps
        return (slice(None), slice(None), slice(top, top + h), slice(left, left + w))

    def full_weight(self) -> torch.Tensor:
        """The whole kernel (out, in, kh, kw): the trained taps set into the untrained rest (differentiable)."""
        if self.taps is None:
            return self.weight
        full = self.kernel.clone()
        full[self.window] = self.weight
        return full

    def _conv_forward(self, input: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        if self.taps is not None:
            if input.shape[-2:] == self.taps[2:]:
                return F.conv2d(input, weight, bias)
            weight = self.full_weight()
        return super()._conv_forward(input, weight, bias)

    def _apply(self, fn: Any, recurse: bool = True) -> Conv2d:
        super()._apply(fn, recurse)
        if self.kernel is not None:
            self.kernel = fn(self.kernel)
        return self


def crop_optimizer_state(model: nn.Module, params: Sequence[nn.Parameter], state: dict[str, Any]) -> int:
    """Crop what an optimizer's state dict holds for whole kernels that now train only some taps.

    A checkpoint of a model that trained the whole kernels holds Adam moments of the whole kernels; PyTorch
    would load them beside the smaller parameters without a word, and the fused Adam would read the wrong
    entries. The moments of the untrained taps are zero (they never had a gradient), so cropping loses nothing.

    Args:
        model: the module holding the convolutions; params: the optimizer's parameters in its group order;
        state: the optimizer's ``state_dict()`` to be loaded (``"state"`` keyed by position in ``params``); its
            fitted entries are replaced (new dicts), others are left as they are.

    Returns:
        How many tensors were cropped.
    """
    by_param = {id(m.weight): m for m in model.modules() if isinstance(m, Conv2d) and m.taps is not None}
    order = [i for group in state.get("param_groups", []) for i in group["params"]]
    cropped = 0
    for index, param in zip(order, params):
        conv = by_param.get(id(param))
        entry = state.get("state", {}).get(index)
        if conv is None or not entry:
            continue
        fitted = dict(entry)  # a new entry: a live optimizer's state_dict() shares its entries with it
        for key, value in entry.items():
            if isinstance(value, torch.Tensor) and value.shape == conv.kernel.shape:
                fitted[key] = value[conv.window].clone()
                cropped += 1
        state["state"][index] = fitted
    return cropped


def _save_full_kernel(module: Conv2d, state_dict: dict[str, Any], prefix: str, local_metadata: Any) -> None:
    """State-dict hook: the whole kernel under ``weight``, as a plain ``nn.Conv2d`` saves it."""
    if module.taps is not None and prefix + "weight" in state_dict:
        state_dict[prefix + "weight"] = module.full_weight().detach()


def _load_full_kernel(module: Conv2d, state_dict: dict[str, Any], prefix: str, *_: Any) -> None:
    """Load-state-dict pre-hook: a whole kernel fills the untrained rest and leaves its trained taps to load."""
    key = prefix + "weight"
    value = state_dict.get(key)
    if module.taps is None or not isinstance(value, torch.Tensor) or value.shape != module.kernel.shape:
        return  # anything else is load_state_dict's to accept or report
    with torch.no_grad():
        module.kernel.copy_(value)
    state_dict[key] = value[module.window]  # load_state_dict works on its own copy


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

    The features are the globally averaged output of the last stage (the paper's), or of several stages side by
    side (``pooled``): an earlier stage keeps more of what pixel statistics say (e.g. an object's colour) than the
    last, whose 1 x 1 map at 32 px is what the pose and shape need.

    Args:
        width: channels of the stem and the first stage, doubled at each later stage (64: ResNet-18 as
            published and as UNICORN uses it). Half the width is a quarter of the multiply-adds; every preset
            keeps 64 (the two compared: ``docs/performance.md``, "Settings that trade speed").
        image_size: the side of the square images it will be trained on, if known: convolutions whose single
            output pixel meets zero padding at that size then train only the taps that meet the image
            (:meth:`Conv2d.keep_taps_for`; layer 4 at 32 px). The outputs, gradients and state dict are those
            of the full network; images of other sizes still run it whole.
        pooled: the stages (:data:`STAGES`) whose globally averaged outputs are concatenated, in network order,
            into the features; ``("layer4",)``: the paper's.

    Shapes:
        (B, 3, H, W) -> (B, F), ``out_features`` F the pooled stages' channels (``8 * width`` for the last alone).
        A 64x64 input gives a 2x2 map before pooling.
    """

    def __init__(self, width: int = 64, image_size: int | None = None, pooled: Sequence[str] = ("layer4",)) -> None:
        super().__init__()
        if width < 1:
            raise ValueError(f"encoder width must be at least 1, got {width}")
        if not distinct_stages(pooled):
            raise ValueError(f"encoder pooled stages must be distinct names of {list(STAGES)}, got {list(pooled)}")
        w = int(width)
        self.pooled = tuple(name for name in STAGES if name in pooled)
        self.out_features = sum(w * 2 ** STAGES.index(name) for name in self.pooled)
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
        if image_size is not None:
            self._keep_taps_for(int(image_size))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_shape(x, "B, 3, H, W", "images")
        out = list(self.stage_means(x, self.pooled).values())
        return torch.cat(out, 1) if len(out) > 1 else out[0]

    def stage_means(self, x: torch.Tensor, names: Sequence[str]) -> dict[str, torch.Tensor]:
        """The named stages' outputs, each averaged over its map: (B, 3, H, W) -> {name: (B, C_name)}, in network
        order; the stages after the last named one do not run.

        Raises:
            ValueError: one image in training mode whose last stage's map is 1 x 1 (at most 32 px for the last
                stage): BatchNorm has a single value per channel to normalise.
        """
        last = max(STAGES.index(n) for n in names)
        if self.training and x.shape[0] == 1:
            h, w = x.shape[-2:]
            for _ in range(2 + last):  # the stem's stride-2 convolution and max-pool, then layer2 ... layer4
                h, w = (h + 1) // 2, (w + 1) // 2
            if h * w == 1:
                raise ValueError(
                    f"one {x.shape[-2]} x {x.shape[-1]} image in training mode: the encoder's BatchNorm needs more "
                    f"than one value per channel ({STAGES[last]}'s map is 1 x 1); call model.eval() to predict, or "
                    "pass 2 images or more"
                )
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        out = {}
        for name in STAGES[: last + 1]:
            x = getattr(self, name)(x)
            if name in names:
                out[name] = self.avgpool(x).flatten(1)
        return out

    def _keep_taps_for(self, size: int) -> None:
        """Apply :meth:`Conv2d.keep_taps_for` to every convolution with its input size at ``size`` px images."""
        sizes: dict[nn.Module, tuple[int, int]] = {}

        def record(conv: nn.Module, args: tuple[torch.Tensor, ...]) -> None:
            sizes[conv] = tuple(args[0].shape[-2:])

        convs = [m for m in self.modules() if isinstance(m, Conv2d)]
        hooks = [c.register_forward_pre_hook(record) for c in convs]
        training = self.training
        try:  # one dry run in eval mode (no BatchNorm statistics change) records what each convolution sees
            self.eval()
            with torch.no_grad():
                self(torch.zeros(1, 3, size, size))
        finally:
            self.train(training)
            for h in hooks:
                h.remove()
        for c in convs:
            c.keep_taps_for(*sizes[c])

    def load_torchvision_state_dict(self, state_dict: Mapping[str, torch.Tensor]) -> None:
        """Load a torchvision ``resnet18`` state dict (``fc.*`` entries dropped), strictly otherwise."""
        kept = {k: v for k, v in state_dict.items() if not k.startswith("fc.")}
        self.load_state_dict(kept, strict=True)
