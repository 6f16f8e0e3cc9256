"""Thread pools sized to the cores this process may actually use.

numba and torch size their pools to the machine's CPU count. On a shared machine that is
too many: a sweep of N jobs, two workers side by side, a SLURM job or container limited by
CPU affinity or a cgroup CPU quota. numba's parallel kernels are split evenly over its
worker threads, which wait on each other at the end of each kernel; when the OS runs
something else on an oversubscribed core, every thread waits for the slowest one, and a run
can get several times slower than with fewer threads.

:func:`available_cores` is the number of cores this process may use: ``GCGS_THREADS`` if
set, else the smaller of the CPU affinity and the cgroup CPU quota (rounded up).
:func:`configure_threads` sizes numba's and torch's pools to it, leaving alone what a user
set explicitly (``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``);
``GCGS_THREADS`` overrides those. ``gcgs`` calls it before running a command.
"""
from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path

from pipeline.errors import ConfigError

ENV_VAR = "GCGS_THREADS"


def _env_threads(env: Mapping[str, str]) -> int | None:
    """``GCGS_THREADS`` as a positive int, None when unset; anything else is a ConfigError."""
    if ENV_VAR not in env:
        return None
    value = env[ENV_VAR]
    try:
        n = int(value.strip())
    except ValueError:
        n = 0
    if n < 1:
        raise ConfigError(f"{ENV_VAR}={value!r}: need a positive whole number of threads")
    return n


def _affinity() -> tuple[int, str]:
    try:
        n = len(os.sched_getaffinity(0))
        return n, f"CPU affinity ({n} of {os.cpu_count()} CPUs)"
    except (AttributeError, OSError):  # not Linux
        n = os.cpu_count() or 1
        return n, f"CPU count ({n})"


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return None


def _quota_v2(path: Path) -> float | None:
    """CPUs allowed by a cgroup v2 ``cpu.max`` ("QUOTA PERIOD" or "max PERIOD")."""
    text = _read(path)
    if text is None:
        return None
    fields = text.split()
    if len(fields) != 2 or fields[0] == "max":
        return None
    try:
        quota, period = int(fields[0]), int(fields[1])
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def _quota_v1(folder: Path) -> float | None:
    """CPUs allowed by cgroup v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (quota -1: none)."""
    quota, period = _read(folder / "cpu.cfs_quota_us"), _read(folder / "cpu.cfs_period_us")
    if quota is None or period is None:
        return None
    try:
        q, p = int(quota.strip()), int(period.strip())
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def _own_cgroups(proc_root: Path) -> tuple[str | None, str | None]:
    """This process's cgroup path for v2 and for v1's ``cpu`` controller (``/proc/self/cgroup``)."""
    v2 = v1 = None
    for line in (_read(proc_root / "proc" / "self" / "cgroup") or "").splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":
            v2 = parts[2]
        elif "cpu" in parts[1].split(","):
            v1 = parts[2]
    return v2, v1


def _chain(mount: Path, own: str | None) -> list[Path]:
    """The cgroup folder at the mount point, and (where known and present) the process's own
    cgroup and its ancestors: a parent's quota limits its children."""
    folders = [mount]
    if own:
        parts = [p for p in own.strip().split("/") if p and p not in (".", "..")]
        folders += [mount.joinpath(*parts[:i]) for i in range(1, len(parts) + 1)]
    return folders


def _cgroup_quota(proc_root: Path) -> tuple[float, str] | None:
    """The tightest cgroup CPU quota (in CPUs) and the file that sets it; None without one."""
    cgroup = proc_root / "sys" / "fs" / "cgroup"
    own_v2, own_v1 = _own_cgroups(proc_root)
    found: list[tuple[float, Path]] = []
    for folder in _chain(cgroup, own_v2):
        if (q := _quota_v2(folder / "cpu.max")) is not None:
            found.append((q, folder / "cpu.max"))
    for mount in (cgroup / "cpu", cgroup / "cpu,cpuacct"):
        for folder in _chain(mount, own_v1):
            if (q := _quota_v1(folder)) is not None:
                found.append((q, folder / "cpu.cfs_quota_us"))
    if not found:
        return None
    q, path = min(found, key=lambda f: f[0])
    return q, f"cgroup CPU quota {q:g} CPUs ({path.relative_to(proc_root)})"


def available_cores(env: Mapping[str, str] = os.environ, proc_root: Path = Path("/"),
                    affinity: int | None = None) -> tuple[int, str]:
    """The number of cores this process may use, and where that number comes from.

    ``GCGS_THREADS`` if set (a positive int, else :class:`ConfigError`); otherwise the
    smaller of the CPU affinity (``affinity`` if given, for tests) and the cgroup CPU quota
    under ``proc_root`` rounded up; never less than 1. Unreadable or garbled cgroup files
    count as no quota.
    """
    n = _env_threads(env)
    if n is not None:
        return n, f"{ENV_VAR}={n}"
    cores, reason = (affinity, f"CPU affinity ({affinity} CPUs)") if affinity is not None else _affinity()
    quota = _cgroup_quota(Path(proc_root))
    if quota is not None and math.ceil(quota[0]) < cores:
        cores, reason = math.ceil(quota[0]), quota[1]
    return max(1, cores), reason


def configure_threads(env: Mapping[str, str] = os.environ) -> int:
    """Size numba's and torch's intra-op thread pools to :func:`available_cores`.

    numba keeps a ``NUMBA_NUM_THREADS`` the user set (it read it at import); otherwise it
    gets the available cores, at most its pool size ``numba.config.NUMBA_NUM_THREADS``.
    numba's setting holds for the calling thread (numba's own rule), which is the one that
    runs a command. torch is left alone when ``OMP_NUM_THREADS`` or ``MKL_NUM_THREADS`` is
    set. ``GCGS_THREADS`` overrides all three. Returns numba's thread count in effect.
    """
    n, _ = available_cores(env)
    override = ENV_VAR in env
    numba_free = override or "NUMBA_NUM_THREADS" not in env
    torch_free = override or not ("OMP_NUM_THREADS" in env or "MKL_NUM_THREADS" in env)
    # A library the command has not imported yet reads these at its import; one it has
    # imported is set directly (importing it here would cost a command that never uses it ~1.5 s).
    if "numba" not in sys.modules:
        if numba_free and env is os.environ:
            os.environ["NUMBA_NUM_THREADS"] = str(n)
        numba_threads = n if numba_free else int(env["NUMBA_NUM_THREADS"])
    else:
        import numba

        numba_threads = max(1, min(n, numba.config.NUMBA_NUM_THREADS)) if numba_free else numba.get_num_threads()
        if numba_free:
            numba.set_num_threads(numba_threads)
    if "torch" not in sys.modules:
        if torch_free and env is os.environ:
            os.environ["OMP_NUM_THREADS"] = str(n)
    elif torch_free:
        import torch

        torch.set_num_threads(n)
    return numba_threads
