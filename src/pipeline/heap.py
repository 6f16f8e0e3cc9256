"""Freed memory kept in the process's heap, so that a training loop does not fault its
buffers in again at every iteration.

Each render allocates a few dozen arrays of 1-30 MB (maps, the tile lists, the per-surfel
set-up) and frees them by the next. glibc serves such sizes with ``mmap`` or gives the top
of its heap back to the OS when freed (``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``, both
adjusted on the fly), so the next iteration takes the pages again and the kernel zeroes each
of them: ~630 page faults and ~10 ms of system time per render at 800x600 / 200k surfels on
the 2-core machines, 4% of its CPU. :func:`keep_freed_memory` raises both thresholds: blocks
up to 32 MiB (glibc's ceiling for the first) come from the heap, and freed memory stays in
it for the next allocation. The process's memory then stays at its high-water mark instead
of shrinking between iterations, which a training process reaches in its first iterations
anyway. ``gcgs`` calls it before running a command.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from collections.abc import Mapping

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 2**20  # the most glibc accepts (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD_BYTES = 2**30


def _user_set(env: Mapping[str, str]) -> bool:
    """Whether the user tuned glibc's allocator through the environment (then it stays theirs)."""
    return "GLIBC_TUNABLES" in env or any(k.startswith("MALLOC_") and k.endswith("_") for k in env)


def keep_freed_memory(env: Mapping[str, str] = os.environ) -> bool:
    """Raise glibc's mmap and trim thresholds for this process; True when they were set.

    Does nothing (False) outside Linux with glibc, or when ``GLIBC_TUNABLES`` or a
    ``MALLOC_*_`` variable is set: the user chose the allocator's settings."""
    if not sys.platform.startswith("linux") or _user_set(env):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # glibc only: musl's mallopt accepts and ignores these
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
