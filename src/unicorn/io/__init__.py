"""Files in and out: checkpoints of every format, textured meshes, user images framed like the training data.

- ``checkpoints``: :func:`load_model` reads any checkpoint (ours, Lightning's, released UNICORN); :func:`save_model`.
- ``reference_checkpoints``: the released UNICORN ``.pkl`` files converted to our model.
- ``serialization``: reads that cannot run code, content hashes, atomic writes (every checkpoint goes through it).
- ``meshes``: predictions as textured meshes, written as OBJ (+ MTL, PNG) or GLB.
- ``images``: user images framed like the training data; ``provenance``: what made an output.
"""

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
from unicorn.io.meshes import export_prediction, glb_bytes, save_mesh, textured_mesh
from unicorn.io.reference_checkpoints import (
    ReferenceCheckpointError,
    config_from_reference,
    convert_reference_state_dict,
    load_reference_checkpoint,
)

__all__ = [
    "CheckpointError",
    "CheckpointInfo",
    "CorruptCheckpointError",
    "InputImage",
    "RawInput",
    "ReferenceCheckpointError",
    "UnsafeCheckpointError",
    "alpha_bbox",
    "collect_inputs",
    "config_from_reference",
    "convert_reference_state_dict",
    "export_prediction",
    "frame_input",
    "glb_bytes",
    "load_input",
    "load_model",
    "load_reference_checkpoint",
    "preprocess",
    "read_checkpoint",
    "read_input",
    "save_mesh",
    "save_model",
    "textured_mesh",
]
