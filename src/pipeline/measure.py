"""Wall time, CPU time and peak resident memory, measured the same way by every stage and
benchmark, so that their figures compare.

* Wall time: ``time.perf_counter``; CPU time: user + system time of all the process's
  threads.
* Peak RSS: Linux's ``VmHWM`` (``/proc/self/status``), the peak resident set size of the
  process's current address space. Not ``ru_maxrss``: across ``exec`` Linux carries the
  pre-exec peak into it, so a child started from a large parent would report at least the
  parent's size. ``VmHWM`` starts afresh at ``exec``, and writing ``5`` to
  ``/proc/self/clear_refs`` resets it to the current RSS, which is how :func:`measure`
  gets the peak of one block of code.
* A child: :func:`run_in_child` runs a function in a fresh interpreter (``spawn``: fork +
  exec, nothing inherited from this process's memory) which measures itself: its peak and
  CPU time are the whole child's, imports included, like a command's.

Sizes are MB = 2**20 bytes, to 0.1 MB. Where ``/proc`` is not available the memory figures are None.
"""
from __future__ import annotations

import ctypes
import gc
import multiprocessing
import os
import platform
import resource
import subprocess
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

_STATUS = Path("/proc/self/status")


def _status_mb(field: str) -> float | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(field + ":"):
                return round(int(line.split()[1]) / 1024.0, 1)  # kB
    except OSError:
        pass
    return None


def peak_rss_mb() -> float | None:
    """This process's peak resident memory (MB) since its exec or the last :func:`reset_peak_rss`."""
    return _status_mb("VmHWM")


def rss_mb() -> float | None:
    """This process's resident memory now (MB)."""
    return _status_mb("VmRSS")


def cpu_s() -> float:
    """User + system CPU seconds of this process (all threads) so far."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def reset_peak_rss() -> bool:
    """Reset this process's peak RSS to its current RSS, after a garbage collection and
    returning freed heap pages to the OS (so that memory reused by the next block shows as
    new). False where the kernel does not allow it: the peak then stays the process's."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


@dataclass
class Usage:
    """What one measured piece of work used.

    ``peak_rss_mb``: peak resident memory of the process while it ran (the whole process's
    memory, not only what the piece allocated); ``start_rss_mb``: resident memory when it
    started, so ``peak_rss_mb - start_rss_mb`` is what the piece added at its peak;
    ``peak_is_own``: False when the peak could not be reset and may come from earlier work
    of the process."""

    wall_s: float = float("nan")
    cpu_s: float = float("nan")
    peak_rss_mb: float | None = None
    start_rss_mb: float | None = None
    peak_is_own: bool = True

    @property
    def added_mb(self) -> float | None:
        """Peak minus the resident memory at the start (MB)."""
        if self.peak_rss_mb is None or self.start_rss_mb is None:
            return None
        return self.peak_rss_mb - self.start_rss_mb

    def as_dict(self) -> dict:
        """Rounded figures for reports (seconds to 0.01, MB to 0.1)."""
        d = asdict(self)
        for k in ("wall_s", "cpu_s"):
            d[k] = round(d[k], 2)
        for k in ("peak_rss_mb", "start_rss_mb"):
            d[k] = None if d[k] is None else round(d[k], 1)
        return d


@contextmanager
def measure(reset_peak: bool = True) -> Iterator[Usage]:
    """Measure the block: ``with measure() as usage: ...``; ``usage`` is filled in on exit.

    ``reset_peak``: the peak is the block's (see :func:`reset_peak_rss`); False: the peak is
    the process's since its start (what a stage reports about itself)."""
    usage = Usage()
    usage.peak_is_own = reset_peak_rss() if reset_peak else False
    usage.start_rss_mb = rss_mb()
    t0, c0 = time.perf_counter(), cpu_s()
    try:
        yield usage
    finally:
        usage.wall_s = time.perf_counter() - t0
        usage.cpu_s = cpu_s() - c0
        usage.peak_rss_mb = peak_rss_mb()


def _child_main(fn: Callable, args: tuple, kwargs: dict) -> tuple[Any, Usage]:
    # In the child: everything since its exec counts (interpreter start, imports).
    result = fn(*args, **kwargs)
    return result, Usage(wall_s=float("nan"), cpu_s=cpu_s(), peak_rss_mb=peak_rss_mb(), start_rss_mb=None,
                         peak_is_own=True)


def run_in_child(fn: Callable, *args, **kwargs) -> tuple[Any, Usage]:
    """Run ``fn(*args, **kwargs)`` in a fresh Python process; return its result and the
    child's :class:`Usage`: wall time as seen from here (process start included), the
    child's CPU time and peak RSS, imports included. ``fn`` must be importable (a module-level
    function) and its arguments and result picklable; an exception in the child is raised
    here."""
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        result, usage = pool.submit(_child_main, fn, args, kwargs).result()
    usage.wall_s = time.perf_counter() - t0
    return result, usage


def provenance() -> dict:
    """What a measurement ran on: commit (``git describe --dirty``), CPU cores, load
    average (the cores may be shared), Python, date."""
    try:
        commit = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True,
                                check=False).stdout.strip()
    except OSError:
        commit = ""
    return {"commit": commit or "unknown", "cpu_cores": os.cpu_count(), "cpu": platform.processor() or platform.machine(),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "python": platform.python_version(), "date": time.strftime("%Y-%m-%d %H:%M:%S")}
