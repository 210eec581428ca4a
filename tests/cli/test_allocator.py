"""The command-line tools' allocator setting, observed through glibc's own statistics (mallinfo2)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from unicorn.cli.allocator import MMAP_THRESHOLD, OPT_OUT

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's allocator only"
)

# a fresh process: allocate a block above glibc's default mmap threshold and below ours, and report whether
# glibc served it by mmap (mallinfo2().hblks counts the mmapped blocks in use)
PROBE = f"""
import ctypes, json
from unicorn.cli.allocator import tune_allocator
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
tuned = tune_allocator()
before = libc.mallinfo2().hblks
block = libc.malloc({MMAP_THRESHOLD // 2})
during = libc.mallinfo2().hblks
libc.free(block)
print(json.dumps({{"tuned": tuned, "mmapped": during - before}}))
"""


def _probe(**env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != OPT_OUT}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**clean, **env}, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_tuned_allocator_keeps_large_blocks_in_the_heap():
    assert _probe() == {"tuned": True, "mmapped": 0}


def test_opting_out_keeps_glibc_defaults():
    # the oracle: with glibc's defaults the same block is mmapped
    assert _probe(**{OPT_OUT: "0"}) == {"tuned": False, "mmapped": 1}


def test_the_users_own_malloc_settings_are_kept():
    assert _probe(MALLOC_MMAP_THRESHOLD_="131072") == {"tuned": False, "mmapped": 1}
