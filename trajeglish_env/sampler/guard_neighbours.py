"""The obstacles of guarded sampling (:mod:`~trajeglish_env.sampler.guard_geometry`): for each sampled agent,
the boxes of its row that one of its candidates could overlap, nearest first (compiled where numba is
available: :func:`~trajeglish_env.pair_kernels.neighbours`, the same numbers)."""

from __future__ import annotations

import numpy as np

from trajeglish_env.batch_geometry import nearest_first
from trajeglish_env.compiled import overlaps, pair_compiled
from trajeglish_env.sampler.rows import RowStates


def half_diagonal(size: np.ndarray) -> np.ndarray:
    """Radius ``[...]`` of the circle around a box of ``size [...,2]``."""
    return np.hypot(size[..., 0], size[..., 1]) / 2


def neighbours(
    rs: RowStates,
    rr: np.ndarray,
    who: np.ndarray,
    tt: np.ndarray,
    origin: np.ndarray,
    size: np.ndarray,
    extent: np.ndarray,
    latest: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    escape_rule: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The boxes a candidate could overlap: the next state of each agent of the row that has moved in
    this step, the current one of each that has not, within reach of some candidate; agents the
    agent's box overlaps already are left out (no move can undo that overlap), but with ``escape_rule`` one
    that *moved* into it in this step, not an external one, stays, flagged ``[n,K]`` (moving on may
    escape it); ``[n]`` says which agents overlap one. ``latest``:
    :func:`~trajeglish_env.sampler.pair_memo.seen_states`."""
    n = len(rr)
    valid_now, valid_after = rs.valid[rr, :, tt], rs.valid[rr, :, tt + 1]
    now = rs.xyh[rr, :, tt]
    state, present, _, moved = latest
    sizes = rs.size[rr]
    kernels = pair_compiled()
    if kernels is not None:  # the same numbers, compiled (pair_kernels.neighbours)
        into_ok = moved & valid_now & valid_after & ~rs.row_external[rr]
        order, count = np.empty(present.shape, np.int64), np.empty(n, np.int64)
        escape, tangled = np.empty(present.shape, bool), np.empty(n, bool)
        floats = (np.ascontiguousarray(a, np.float64) for a in (origin, size, extent))
        kernels.neighbours(
            *floats,
            who.astype(np.int64),
            np.ascontiguousarray(state, np.float64),
            present,
            sizes,
            *(escape_rule, into_ok, np.ascontiguousarray(now, np.float64), order, count, escape, tangled),
        )
        k = int(count.max(initial=0))
        idx, real = order[:, :k], np.arange(k) < count[:, None]
        rows = np.arange(n)[:, None]
        return state[rows, idx], sizes[rows, idx], real, escape[rows, idx] & real, tangled
    d = np.hypot(state[..., 0] - origin[:, None, 0], state[..., 1] - origin[:, None, 1])
    near = present & (d < extent[:, None] + half_diagonal(sizes))
    near[np.arange(n), who] = False
    tangled = np.zeros(n, bool)
    i, j = np.nonzero(near)
    escape = np.zeros_like(near)
    if len(i):
        overlap = overlaps(origin[i], size[i], state[i, j], sizes[i, j])
        if escape_rule:
            # moved into it this step: there before and overlapping now, not then (a pair overlapping
            # from the start, parked boxes of a log, stays tangled; so does one appearing on it); an
            # external agent's collision is its own
            into = overlap & moved[i, j] & valid_now[i, j] & valid_after[i, j] & ~rs.row_external[rr[i], j]
            q = np.flatnonzero(into)
            before = overlaps(origin[i[q]], size[i[q]], now[i[q], j[q]], sizes[i[q], j[q]])
            into[q[before]] = False
            escape[i, j] = into
        near[i, j] = ~overlap | escape[i, j]
        tangled[i[overlap]] = True
    k = int(near.sum(axis=1).max(initial=0))
    if k == 0:
        empty = np.zeros((n, 0), bool)
        return np.zeros((n, 0, 3)), np.ones((n, 0, 2)), empty, empty, tangled
    idx, real = nearest_first(np.where(near, d, np.inf), k)
    rows = np.arange(n)[:, None]
    return state[rows, idx], sizes[rows, idx], real, escape[rows, idx] & real, tangled
