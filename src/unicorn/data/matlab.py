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
from scipy.io.matlab import MatReadError

from unicorn.data.images import DatasetError
from unicorn.errors import UserError

__all__ = ["MatFileError", "MissingVariableError", "load_struct_array", "read_mat"]


class MissingVariableError(UserError, KeyError):
    """A MATLAB annotation file without the variable its dataset needs (a malformed or foreign file)."""


class MatFileError(DatasetError):
    """A file that scipy cannot read as a MATLAB (v4 to v7.2) file: truncated, another format, a folder."""


def read_mat(path: str | os.PathLike, **options: Any) -> dict[str, Any]:
    """``scipy.io.loadmat(path, **options)``, its failures one :class:`MatFileError` naming the file.

    Raises:
        MatFileError: the file is not a readable MATLAB file (v7.3 files are HDF5, which scipy does not read).
    """
    try:
        return scipy.io.loadmat(path, **options)
    except NotImplementedError as err:  # scipy's words for a v7.3 (HDF5) file
        raise MatFileError(f"cannot read {path}: a MATLAB v7.3 file; save it with -v7 ({err})") from None
    except (MatReadError, OSError, ValueError, TypeError, IndexError, KeyError, EOFError) as err:  # bad bytes
        reason = str(err) or type(err).__name__
        raise MatFileError(f"cannot read {path} as a MATLAB file: {reason}") from None


def load_struct_array(path: str | os.PathLike, variable: str) -> list[dict[str, Any]]:
    """Load a MATLAB struct array as a list of dicts, one per record.

    Args:
        path: .mat file.
        variable: name of the struct-array variable, e.g. ``"images"``.

    Returns:
        One dict per record, even when the file holds a single record.

    Raises:
        MatFileError: the file cannot be read as a MATLAB file.
        MissingVariableError: the file has no such variable (the message lists the variables it has).
    """
    data = read_mat(path, simplify_cells=True)
    if variable not in data:
        names = sorted(k for k in data if not k.startswith("__"))
        raise MissingVariableError(f"{path} has no variable {variable!r} (it has {names})")
    records = data[variable]
    if isinstance(records, dict):  # a single record
        return [records]
    return list(np.asarray(records, dtype=object).ravel())
