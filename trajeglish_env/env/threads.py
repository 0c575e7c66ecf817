"""Torch threads of a batch of scenes: ``"auto"`` uses several on an idle machine and one as soon as other
processes compete for the cores (multi-threaded small decoding calls spin-wait and collapse on a shared
machine: measured 4-9x slower than one thread with one other busy process). It starts on one thread and
adds the others only once a look at the machine finds the cores free, so a busy machine never sees them.

The thread count never changes a sampled token (tested), so it may change between steps. An env applies its
count only while it runs the model (:func:`torch_threads_scope`): the caller's own torch work (a learner in
the same process) keeps the caller's setting."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

from trajeglish_env.cores import cpu_seconds, threads_for, usable_cores

__all__ = [
    "CHECK_EVERY_S",
    "FIRST_CHECK_S",
    "AdaptiveThreads",
    "auto_threads",
    "cpu_seconds",
    "threads_for",
    "torch_threads_scope",
    "usable_cores",
]

CHECK_EVERY_S = 2.0  # seconds of stepping between two looks at the machine's load
# the first look comes sooner: a batch now steps a whole 18-step window cycle in well under 2 s, which it
# would otherwise spend with too many threads beside a busy process (B = 8: 0.33x its idle speed)
FIRST_CHECK_S = 0.25


def auto_threads(num_scenes: int, cores: int | None = None) -> int:
    """Threads for a batch on an idle machine: 2 up to 8 scenes (a single env's call decodes about 48
    positions, its step's and the look-ahead's: one scene +8-16 % on a second core, 3 scenes +16 %; 4 scenes
    in bfloat16 +24 %), one per 4 scenes beyond 8, up to the usable cores."""
    return max(1, min(cores or usable_cores(), max(2, num_scenes // 4)))


@contextmanager
def torch_threads_scope(threads: int | None) -> Iterator[None]:
    """Torch runs ``threads`` intra-op threads inside the block and the caller's count again after it
    (None: torch is left alone). Setting the count costs well under a microsecond."""
    if threads is None:
        yield
        return
    import torch

    before = torch.get_num_threads()
    if before != threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


class AdaptiveThreads:
    """The ``"auto"`` policy: :func:`auto_threads` threads while the cores are free for this process,
    fewer (down to one) while other processes keep them busy; one until the first check, due
    :data:`FIRST_CHECK_S` seconds after it starts, then checked every ``every_s`` seconds of stepping,
    from the machine's CPU time minus this process's own. It decides ``threads``; the env applies it in a
    :func:`torch_threads_scope`."""

    def __init__(self, num_scenes: int, every_s: float = CHECK_EVERY_S):
        self.cores = usable_cores()
        self.wanted = auto_threads(num_scenes, self.cores)
        self.every_s = every_s
        self.threads = 1  # more only once a look finds the cores free (a busy machine never sees them)
        self._mark = (time.perf_counter(), cpu_seconds())
        self._interval = min(FIRST_CHECK_S, every_s)

    def tick(self) -> None:
        """Call once per batch step: adjust the thread count when a check is due."""
        if self.wanted == 1:
            return
        now, then = time.perf_counter(), self._mark
        if now - then[0] < self._interval:
            return
        self._interval = self.every_s
        cpu = cpu_seconds()
        if cpu is not None and then[1] is not None:
            others = ((cpu[0] - then[1][0]) - (cpu[1] - then[1][1])) / (now - then[0])
            threads = threads_for(max(others, 0.0), self.wanted, self.cores)
            self.threads = threads
        self._mark = (now, cpu)
