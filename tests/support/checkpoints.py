"""State dicts in the released checkpoints' names and shapes (and torchvision's), files that run code when unpickled."""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path
from typing import Any

import torch


def torchvision_resnet18_shapes() -> dict[str, tuple[int, ...]]:
    """Key names and shapes of torchvision's resnet18 state dict, written out from its layout."""
    shapes: dict[str, tuple[int, ...]] = {"conv1.weight": (64, 3, 7, 7)}

    def bn(prefix: str, c: int) -> None:
        for name in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{name}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    bn("bn1", 64)
    cin = 64
    for i, c in enumerate((64, 128, 256, 512), start=1):
        for j in range(2):
            p = f"layer{i}.{j}"
            shapes[f"{p}.conv1.weight"] = (c, cin if j == 0 else c, 3, 3)
            bn(f"{p}.bn1", c)
            shapes[f"{p}.conv2.weight"] = (c, c, 3, 3)
            bn(f"{p}.bn2", c)
            if j == 0 and i > 1:
                shapes[f"{p}.downsample.0.weight"] = (c, cin, 1, 1)
                bn(f"{p}.downsample.1", c)
        cin = c
    shapes["fc.weight"] = (1000, 512)
    shapes["fc.bias"] = (1000,)
    return shapes


_RESNET_INDEX = {"conv1": 0, "bn1": 1, "layer1": 4, "layer2": 5, "layer3": 6, "layer4": 7}


def _mlp(prefix: str, n_in: int, n_out: int, units: int = 128, layers: int = 3) -> dict[str, tuple[int, ...]]:
    dims = [n_in] + [units] * layers + [n_out]
    shapes = {}
    for i in range(layers + 1):
        shapes[f"{prefix}.{2 * i}.weight"] = (dims[i + 1], dims[i])
        shapes[f"{prefix}.{2 * i}.bias"] = (dims[i + 1],)
    return shapes


def _generator(prefix: str, code: int, size: int, min_features: int) -> dict[str, tuple[int, ...]]:
    n_blocks = int(math.log2(size))

    def nch(i: int) -> int:
        return max(code // 2**i, min_features)

    shapes = _mlp(f"{prefix}.regressor", 512, code)
    shapes[f"{prefix}.generator.conv_layers.0.weight"] = (code // 2, code, 3, 3)
    for i in range(n_blocks - 1):
        shapes[f"{prefix}.generator.conv_layers.{i + 1}.weight"] = (nch(i + 2), nch(i + 1), 3, 3)
    shapes[f"{prefix}.generator.conv_rgb.0.weight"] = (3, code, 3, 3)
    for i in range(n_blocks):
        shapes[f"{prefix}.generator.conv_rgb.{i + 1}.weight"] = (3, nch(i + 1), 3, 3)
    shapes[f"{prefix}.generator.upsample_rgb.1.kernel"] = (1, 1, 3, 3)
    return shapes


def reference_state(big: bool = False, background: bool = True, field_units: int = 128) -> dict[str, torch.Tensor]:
    """A state dict in the reference's key names and shapes (image 32 px, texture 16 px), random values."""
    sh, tx, bg, minf = (64, 512, 256, 64) if big else (32, 128, 128, 16)
    shapes: dict[str, tuple[int, ...]] = {}
    encoders = (
        (["encoder_sh", "encoder_tx", "encoder_pose"] + (["encoder_bg"] if background else [])) if big else ["encoder"]
    )
    for enc in encoders:
        for key, shape in torchvision_resnet18_shapes().items():
            head, rest = key.split(".", 1)
            if head != "fc":
                shapes[f"{enc}.encoder.{_RESNET_INDEX[head]}.{rest}"] = shape
    shapes.update(_mlp("deform_field.regressor", 512, sh))
    shapes.update(
        {"deform_field.field.linear_x.weight": (field_units, 3), "deform_field.field.linear_x.bias": (field_units,)}
    )
    shapes.update(
        {"deform_field.field.linear_z.weight": (field_units, sh), "deform_field.field.linear_z.bias": (field_units,)}
    )
    shapes.update(_mlp("deform_field.field.mlp", field_units, 3, field_units, 2))
    shapes.update(_generator("txt_generator", tx, 16, minf))
    if background:
        shapes.update(_generator("bkg_generator", bg, 32, minf))
    for k in range(6):
        shapes.update(_mlp(f"rot_regressors.{k}", 512, 3))
        shapes.update(_mlp(f"T_regressors.{k}", 512, 3))
    shapes.update(_mlp("scale_regressor", 512, 3))
    shapes.update(_mlp("proba_regressor", 512, 6))
    for i, (cin, cout) in {0: (3, 64), 2: (64, 64), 5: (64, 128), 7: (128, 128), 10: (128, 256)}.items():
        slice_id = 1 if i < 4 else (2 if i < 9 else 3)
        shapes[f"perceptual_loss.slice{slice_id}.{i}.weight"] = (cout, cin, 3, 3)
        shapes[f"perceptual_loss.slice{slice_id}.{i}.bias"] = (cout,)
    for i in (12, 14):
        shapes[f"perceptual_loss.slice3.{i}.weight"] = (256, 256, 3, 3)
        shapes[f"perceptual_loss.slice3.{i}.bias"] = (256,)
    shapes.update({"uvs": (1, 642, 2), "R_init": (6, 3), "R_range": (1, 3), "T_init": (3,), "T_range": (3,)})
    shapes.update({"scale_init": (3,), "scale_range": (3,)})
    g = torch.Generator().manual_seed(0)
    state = {}
    for key, shape in shapes.items():
        state[key] = torch.tensor(3) if key.endswith("num_batches_tracked") else torch.randn(shape, generator=g) * 0.05
        if key.endswith("running_var"):
            state[key] = state[key].abs() + 1.0
    return state


class Payload:
    """Unpickling this runs ``os.system``: it creates ``marker`` (the shell command of a malicious file)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def malicious(path: Path, marker: Path, data: dict | None = None) -> Path:
    """Save ``data`` (default: a small dict) with a payload inside it."""
    torch.save({**(data or {"weights": torch.zeros(2)}), "epoch": Payload(marker)}, path)
    return path


def deflated_torch_file(obj: Any, path: Path) -> Path:
    """``torch.save`` of ``obj`` re-packed with compressed (deflated) zip entries, which ``torch.save`` never writes
    and ``torch.load`` would inflate in memory before anything is checked: a decompression bomb's layout."""
    saved = path.with_name(path.name + ".stored")
    torch.save(obj, saved)
    with zipfile.ZipFile(saved) as zin, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zout:
        for entry in zin.infolist():
            zout.writestr(entry.filename, zin.read(entry.filename))
    saved.unlink()
    return path
