"""The machine's cores as this package's parallel paths see them: how many this process may use, and how
many other processes keep busy (the env's adaptive torch threads, multi-process rollouts)."""

from __future__ import annotations

import math
import multiprocessing
import os
import sys
import time
from pathlib import Path


def usable_cores() -> int:
    """Cores this process may run on: those it is pinned to, at most its container's CPU quota (a cgroup's
    ``cpu.max``, as ``docker --cpus=2`` sets it; rounded up)."""
    pinned = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    quota = cgroup_cpu_quota()
    return max(1, min(pinned, math.ceil(quota))) if quota is not None else pinned


def cgroup_cpu_quota(root: str = "/sys/fs/cgroup") -> float | None:
    """The CPUs this process's cgroup may use (cgroup v2 ``cpu.max``, or v1's ``cpu.cfs_quota_us`` over
    ``cpu.cfs_period_us``); None without a quota or where none is readable."""
    base = Path(root)
    try:
        quota, period = (base / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us = int((base / "cpu" / "cpu.cfs_quota_us").read_text())
        period_us = int((base / "cpu" / "cpu.cfs_period_us").read_text())
        return quota_us / period_us if quota_us > 0 and period_us > 0 else None
    except (OSError, ValueError):
        return None


def cpu_seconds() -> tuple[float, float] | None:
    """(CPU seconds used by every process of the machine, by this process) so far; None where the machine's
    total is not readable (non-Linux)."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    busy = sum(fields) - fields[3] - fields[4]  # all but idle and iowait
    own = os.times()
    return busy / os.sysconf("SC_CLK_TCK"), own.user + own.system


def threads_for(others_busy: float, wanted: int, cores: int) -> int:
    """Threads that fit beside ``others_busy`` cores kept busy by other processes."""
    free = cores - others_busy
    return max(1, min(wanted, int(free + 0.25)))


def others_busy_cores(window_s: float = 0.25) -> float:
    """Cores other processes kept busy over the next ``window_s`` seconds (this process sleeps meanwhile;
    0 where the machine's CPU time is not readable)."""
    before, start = cpu_seconds(), time.perf_counter()
    time.sleep(window_s)
    after, elapsed = cpu_seconds(), time.perf_counter() - start
    if before is None or after is None:
        return 0.0
    return max(0.0, ((after[0] - before[0]) - (after[1] - before[1])) / elapsed)


def can_fork() -> bool:
    """Whether work may be split over forked processes (rollouts, scenes of a batched env): on Linux
    (macOS forks, but its system libraries are not safe to use in a forked child)."""
    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


def native_bfloat16() -> bool:
    """Whether this machine's CPU multiplies bfloat16 matrices natively (oneDNN says so)."""
    import torch

    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False
