"""glibc's allocator thresholds for the command-line tools: keep freed memory for reuse.

A training step allocates and frees the same large buffers every iteration (parameter gradients, activations,
the full-size weight gradients of the encoder's cropped 1-pixel convolutions). glibc hands every block above
its mmap threshold (128 KiB at first, raised only to the size of the largest block freed so far) to the kernel
and back, so each step page-faults those buffers in again (what that costs: ``docs/performance.md``).
Raising the threshold to glibc's maximum (32 MiB) and the trim threshold to 256 MiB keeps them in the heap; the
values computed are the same, the process may hold up to the trim threshold of freed memory.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

__all__ = ["MMAP_THRESHOLD", "OPT_OUT", "TRIM_THRESHOLD", "tune_allocator"]

#: blocks below this size come from the heap (glibc refuses more than 32 MiB on 64-bit systems)
MMAP_THRESHOLD = 32 * 1024 * 1024
#: freed memory at the top of the heap is returned to the system only above this much
TRIM_THRESHOLD = 256 * 1024 * 1024
#: set to 0 to keep glibc's defaults
OPT_OUT = "UNICORN_TUNE_MALLOC"

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
_M_MMAP_THRESHOLD = -3


def tune_allocator() -> bool:
    """Raise glibc's mmap and trim thresholds for this process; True if they were set.

    Nothing is changed on other C libraries or systems, when ``UNICORN_TUNE_MALLOC=0``, or when the user set
    glibc's own ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` (theirs are kept).
    """
    if os.environ.get(OPT_OUT, "1") == "0":
        return False
    if any(name in os.environ for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")):
        return False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mallopt returns 1 on success, 0 on an out-of-range value; both are set either way
    results = [mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD), mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)]
    return all(results)
