"""The C heap's policy for the decoding engines: keep freed memory for the next allocation.

glibc serves an allocation above its mmap threshold (128 kB, raised to the largest block freed so far, at
most 32 MB) with fresh pages from the kernel, and gives the top of the heap back once more than its trim
threshold is free. A decoding step allocates and frees the same few-megabyte activations dozens of
times, so every one of them paid the kernel for zeroed pages again: a bfloat16 linear layer of 1,536
rows x 512 took 3.6 ms instead of 0.58 ms, and the env ran 11-13 % slower (measured, 2-core machine).
:func:`keep_freed_memory` raises both thresholds once per process (the whole process: a training loop
beside the env gets them too). It changes no number (where memory comes from, not what is computed); the
peak moved by under 1 % in the env benchmark (B = 128: 718 -> 714 MB), but memory freed after a peak
stays in the process instead of going back to the kernel: up to ``TRIM_MB`` at the top of each heap, and
more in the per-thread arenas glibc keeps anyway (a ``BatchedEgoEnv(96)`` closed and deleted left 1,000 of
its 1,003 MB, with or without this policy). :func:`release_freed_memory` gives the free pages of every
arena back (``malloc_trim``; 0.03 ms): the envs call it when they close, and after dropping an env
(``del env``) it brought a process from 1,000 MB back to 323 MB. ``TRAJEGLISH_KEEP_HEAP=0`` turns the
policy off; on a C library without ``mallopt`` / ``malloc_trim`` (macOS, Windows) both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os

# allocations below this come from the heap (reused) rather than fresh kernel pages; 32 MB is the most
# glibc accepts up to 2.34 (HEAP_MAX_SIZE / 2) and its own dynamic threshold's ceiling on 64-bit
MMAP_MB = 32
TRIM_MB = 256  # free memory at the heap's top kept for reuse before it is given back
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
_done: bool | None = None


def keep_freed_memory() -> bool:
    """Raise the C heap's mmap and trim thresholds for this process (once); whether the policy is in force
    (False where it is turned off or the C library has no ``mallopt``)."""
    global _done
    if _done is None:
        _done = os.environ.get("TRAJEGLISH_KEEP_HEAP", "1") != "0" and _mallopt()
    return _done


def _mallopt() -> bool:
    """Both thresholds set, each on its own (True where both were accepted)."""
    libc = _libc()
    mallopt = getattr(libc, "mallopt", None) if libc is not None else None
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    trim = bool(mallopt(_M_TRIM_THRESHOLD, TRIM_MB << 20))
    mmap = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_MB << 20))
    return trim and mmap


def release_freed_memory() -> bool:
    """Give the C heap's free pages back to the kernel (glibc's ``malloc_trim(0)``, every arena); whether
    it ran. Call it after dropping a large env (``del env``) to shrink the process's resident memory."""
    libc = _libc()
    trim = getattr(libc, "malloc_trim", None) if libc is not None else None
    if trim is None:
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library, found once (``find_library`` runs ``ldconfig``: milliseconds a call)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c"))
    except (OSError, TypeError):
        return None
