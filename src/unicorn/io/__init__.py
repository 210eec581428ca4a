"""Files in and out: checkpoints of every supported format, and user images framed like the training data."""

from unicorn.io.checkpoints import (
    CheckpointError,
    CheckpointInfo,
    CorruptCheckpointError,
    UnsafeCheckpointError,
    load_model,
    read_checkpoint,
    save_model,
)
from unicorn.io.images import (
    InputImage,
    RawInput,
    alpha_bbox,
    collect_inputs,
    frame_input,
    load_input,
    preprocess,
    read_input,
)

__all__ = [
    "CheckpointError",
    "CheckpointInfo",
    "CorruptCheckpointError",
    "InputImage",
    "RawInput",
    "UnsafeCheckpointError",
    "alpha_bbox",
    "collect_inputs",
    "frame_input",
    "load_input",
    "load_model",
    "preprocess",
    "read_checkpoint",
    "read_input",
    "save_model",
]
