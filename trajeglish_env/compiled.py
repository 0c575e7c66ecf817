"""The guard's compiled kernels (:mod:`~trajeglish_env.guard_kernels`, :mod:`~trajeglish_env.pair_kernels`),
imported on first use (numba takes a
third of a second to import, which a user who never samples a guarded step should not pay), and the box
overlaps the guard asks through them."""

from __future__ import annotations

from types import ModuleType

import numpy as np

from trajeglish_env.metrics.boxes import box_collisions

_KERNELS: list[ModuleType] = []
_PAIR_KERNELS: list[ModuleType] = []


def compiled() -> ModuleType | None:
    """:mod:`~trajeglish_env.guard_kernels`, or None where numba is missing or switched off (its
    ``AVAILABLE``; ``TRAJEGLISH_NO_NUMBA=1``): the callers then take their NumPy paths, the same numbers."""
    if not _KERNELS:
        from trajeglish_env import guard_kernels

        _KERNELS.append(guard_kernels)
    return _KERNELS[0] if _KERNELS[0].AVAILABLE else None


def pair_compiled() -> ModuleType | None:
    """:mod:`~trajeglish_env.pair_kernels` (the guard's neighbours, following caps and stall history), or
    None where the kernels are off (as :func:`compiled`)."""
    if compiled() is None:
        return None
    if not _PAIR_KERNELS:
        from trajeglish_env import pair_kernels

        _PAIR_KERNELS.append(pair_kernels)
    return _PAIR_KERNELS[0]


def overlaps(xyh_a: np.ndarray, size_a: np.ndarray, xyh_b: np.ndarray, size_b: np.ndarray) -> np.ndarray:
    """``[n]`` where boxes ``xyh_a [n,3]`` and ``xyh_b [n,3]`` (sizes ``[n,2]``) overlap: the guard's
    :func:`~trajeglish_env.metrics.boxes.box_collisions`, compiled where numba is available (the same
    verdicts)."""
    kernels = compiled()
    if kernels is None or not len(xyh_a):
        return box_collisions(xyh_a, size_a, xyh_b, size_b)
    out = np.empty(len(xyh_a), bool)
    boxes = (np.ascontiguousarray(a, np.float64) for a in (xyh_a, size_a, xyh_b, size_b))
    kernels.box_overlaps(*boxes, out)
    return out
