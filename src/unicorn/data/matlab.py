"""Reading the MATLAB annotation files of CMR / UCMR with ``scipy.io.loadmat``.

``loadmat(..., struct_as_record=False, squeeze_me=True)`` returns struct arrays as numpy object arrays of
``mat_struct``, except that a one-element array collapses to a bare ``mat_struct`` and a MATLAB logical loads
as uint8. These helpers undo both so loaders see a list of plain dicts.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import scipy.io

__all__ = ["load_struct_array", "struct_to_dict"]


def struct_to_dict(struct: Any) -> dict[str, Any]:
    """One ``mat_struct`` to a dict of its fields (nested structs converted too)."""
    out = {}
    for name in struct._fieldnames:
        value = getattr(struct, name)
        if isinstance(value, scipy.io.matlab.mat_struct):
            value = struct_to_dict(value)
        out[name] = value
    return out


def load_struct_array(path: str | os.PathLike, variable: str) -> list[dict[str, Any]]:
    """Load a MATLAB struct array as a list of dicts, one per record.

    Args:
        path: .mat file.
        variable: name of the struct-array variable, e.g. ``"images"``.

    Returns:
        One dict per record, even when the file holds a single record.

    Raises:
        KeyError: if the file has no such variable (the message lists the variables it has).
    """
    data = scipy.io.loadmat(path, struct_as_record=False, squeeze_me=True)
    if variable not in data:
        names = sorted(k for k in data if not k.startswith("__"))
        raise KeyError(f"{path} has no variable {variable!r} (it has {names})")
    records = np.atleast_1d(data[variable])  # a single record loads as a bare struct
    return [struct_to_dict(r) for r in records.ravel()]
