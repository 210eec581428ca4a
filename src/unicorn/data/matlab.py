"""Reading the MATLAB annotation files of CMR / UCMR with ``scipy.io.loadmat(..., simplify_cells=True)``.

scipy turns MATLAB structs into dicts (nested ones too) and squeezes singleton dimensions; the one thing left
to the caller is that a struct array holding one record loads as that record's dict rather than a list of
one, which :func:`load_struct_array` undoes. (A MATLAB logical still loads as uint8.)
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import scipy.io

from unicorn.errors import UserError

__all__ = ["MissingVariableError", "load_struct_array"]


class MissingVariableError(UserError, KeyError):
    """A MATLAB annotation file without the variable its dataset needs (a malformed or foreign file)."""


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
    data = scipy.io.loadmat(path, simplify_cells=True)
    if variable not in data:
        names = sorted(k for k in data if not k.startswith("__"))
        raise MissingVariableError(f"{path} has no variable {variable!r} (it has {names})")
    records = data[variable]
    if isinstance(records, dict):  # a single record
        return [records]
    return list(np.asarray(records, dtype=object).ravel())
