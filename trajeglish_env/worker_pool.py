"""Process pools that stop when their caller stops: Ctrl-C, SIGTERM or the caller's death end the workers
at once, instead of running every queued job first (``ProcessPoolExecutor``'s exit waits for them) or
lingering as orphans.

Workers ignore Ctrl-C (the terminal sends it to the whole process group: the caller handles it), unwind
on SIGTERM (their ``with`` blocks exit: temporary folders removed, tools they run killed) and get SIGTERM
when the caller dies, even by SIGKILL (Linux ``PR_SET_PDEATHSIG``). On any exception in the ``with`` block,
queued jobs are cancelled and the workers terminated (killed if one has not ended after 10 s) before the
exception goes on.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager

__all__ = ["die_with_parent", "worker_pool"]


def die_with_parent(parent: int | None) -> None:
    """Linux: this process gets SIGTERM when the process that started it dies (even by SIGKILL). The kernel
    ties the signal to the starting *thread*, so ``parent`` is None (no signal) when the caller started it
    from another thread than its main one; a caller already gone ends this process at once."""
    if parent is None:
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError, TypeError):
        return
    if os.getppid() != parent:  # the caller died before the signal was armed
        os._exit(1)


def _exit_on_sigterm(signum: int, frame: object) -> None:
    """SIGTERM in a worker unwinds it (``with`` blocks exit: temporary folders removed, a running
    ``subprocess.run`` kills its child) instead of ending it where it stands."""
    raise SystemExit(128 + signum)


def _start_worker(parent: int) -> None:
    """A pool worker's first act: leave Ctrl-C to the caller, clean up on SIGTERM, end with the caller."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):  # held while it started (_HeldSpawnProcess): now dropped
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    die_with_parent(parent)


def _processes(pool: ProcessPoolExecutor) -> list[multiprocessing.process.BaseProcess]:
    """The pool's worker processes (a private attribute of ``ProcessPoolExecutor``; none if it changes)."""
    return list((getattr(pool, "_processes", None) or {}).values())


class _HeldSpawnProcess(multiprocessing.context.SpawnProcess):
    """A spawned worker that starts with Ctrl-C held until :func:`_start_worker` ignores it: a Ctrl-C
    while it imported (seconds) printed its KeyboardInterrupt traceback over the caller's one line."""

    def start(self) -> None:
        held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # the child inherits the mask
        try:
            super().start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)


class _HeldSpawnContext(multiprocessing.context.SpawnContext):
    Process = _HeldSpawnProcess


def _context(method: str) -> multiprocessing.context.BaseContext:
    """``method``'s context; for spawn (POSIX), one whose workers start with Ctrl-C held."""
    if method == "spawn" and hasattr(signal, "pthread_sigmask"):
        return _HeldSpawnContext()
    return multiprocessing.get_context(method)


@contextmanager
def worker_pool(workers: int, method: str = "spawn") -> Iterator[ProcessPoolExecutor]:
    """A ``ProcessPoolExecutor`` of ``workers`` processes (``method``: spawn, no fork of a process that may
    hold torch threads) that is torn down at once when the block raises (Ctrl-C included)."""
    pool = ProcessPoolExecutor(
        max_workers=workers,
        mp_context=_context(method),
        initializer=_start_worker,
        initargs=(os.getpid(),),
    )
    try:
        yield pool
    except BaseException:
        processes = _processes(pool)
        pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + 10  # SIGTERM (they clean up), then SIGKILL for one that will not end
        while [p for p in processes if p.exitcode is None]:
            for process in processes:
                if process.exitcode is None:
                    if time.monotonic() > deadline:
                        process.kill()
                    else:
                        process.terminate()
                    process.join(timeout=0.2)
        raise
    pool.shutdown(wait=True)
