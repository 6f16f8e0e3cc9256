"""pipeline.heap: with the thresholds raised, a buffer freed and taken again is not
faulted in again (the render loop's case); the user's own allocator settings are kept."""
from __future__ import annotations

import subprocess
import sys

import pytest

from pipeline import heap

# Four 24 MB buffers alive at once, touched and freed, 20 times (a render's maps and lists,
# smaller); print the minor page faults of the last 10 rounds.
LOOP = """
import resource, sys
import numpy as np
from pipeline import heap
if sys.argv[1] == "keep":
    assert heap.keep_freed_memory({})
def once():
    bufs = [np.empty(6 * 2**20, np.float32) for _ in range(4)]
    for a in bufs:
        a[::1024] = 1.0  # one write per page
    del bufs, a
for _ in range(10):
    once()
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    once()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", LOOP, mode], capture_output=True, text=True, check=True).stdout
    return int(out.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_freed_buffers_are_not_faulted_in_again():
    default, keep = _faults("default"), _faults("keep")
    assert default > 1000  # glibc gives (some of) them back: faulted in again in each round
    assert keep < default // 100


def test_the_users_allocator_settings_are_kept():
    assert not heap.keep_freed_memory({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0"})
    assert not heap.keep_freed_memory({"MALLOC_TRIM_THRESHOLD_": "0"})
