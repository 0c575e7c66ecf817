"""Per-agent memory of the guard's road-edge answers, kept while the agent stands where it stands.

How far a candidate box lies beyond a road edge, and how far its kept-up motion stays on the road, depend only
on the agent's model state, its box, its class, the candidate token and the map: not on the other agents,
not on the model's logits. Parallel decoding asks them several times for one agent in one step (guarding the
step's drafts, then the model's draws, then again in a call after a cut), and a standing agent asks the same
at every step. Measuring them is most of the guard's cost (road-edge cells: a third of it on the bench's
scenes), so each (row, agent) slot remembers its answers per token, under a *key* of everything they depend on
(state, box, class, map, the cells' epoch); a slot whose key changes is cleared. The answers are the ones a
fresh measurement gives, number for number (each is computed per candidate, independent of the others
measured with it), so nothing sampled changes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from trajeglish_env.compiled import pair_compiled

KEY_WIDTH = 8  # x, y, heading, length, width, class, map index, cells epoch


def memo_keys(
    origin: np.ndarray, size: np.ndarray, kind: np.ndarray, maps: np.ndarray, epoch: int
) -> np.ndarray:
    """``[m,KEY_WIDTH]`` the keys of ``m`` agents at model states ``origin [m,3]`` with boxes ``size [m,2]``,
    classes ``kind [m]``, on maps ``maps [m]`` of the road-edge cells of epoch ``epoch``."""
    m = len(origin)
    return np.column_stack([origin, size, kind, maps, np.full(m, float(epoch))]).astype(np.float64)


class CandidateMemo:
    """Answers ``[B,N,width]`` per (row, agent) slot and entry (a candidate token, or one per-agent answer),
    NaN where not measured yet, each slot valid for its key (:func:`memo_keys`)."""

    def __init__(self) -> None:
        self.keys = np.zeros((0, 0, KEY_WIDTH))
        self.values = np.zeros((0, 0, 0))

    def lookup(
        self,
        rows: np.ndarray,
        agents: np.ndarray,
        keys: np.ndarray,
        entries: np.ndarray,
        want: np.ndarray,
        measure: Callable[[np.ndarray, np.ndarray], np.ndarray],
        width: int,
    ) -> np.ndarray:
        """``[m,c]`` the answers at ``entries [m,c]`` of slots ``(rows, agents) [m]`` (keys ``[m,KEY_WIDTH]``)
        where ``want [m,c]`` (NaN elsewhere); ``measure(i, j)`` answers the entries ``(i, j)`` not
        known yet, which are then kept. ``width``: entries per slot (a slot beyond the memory's, or another
        width, clears it all)."""
        b, n, w = self.values.shape
        if len(rows) and (w != width or rows.max() >= b or agents.max() >= n):
            shape = (max(b, int(rows.max()) + 1), max(n, int(agents.max()) + 1), width)
            self.keys = np.full(shape[:2] + (KEY_WIDTH,), np.nan)
            self.values = np.full(shape, np.nan)
        kernels = pair_compiled()
        if kernels is not None:  # the same answers, compiled (pair_kernels.memo_gather)
            got = np.empty(entries.shape)
            index = (rows.astype(np.int64), agents.astype(np.int64))
            floats = np.ascontiguousarray(keys, np.float64)
            if not kernels.memo_gather(self.keys, self.values, *index, floats, entries, want, got):
                return got
            i, j = np.nonzero(np.isnan(got) & want)
        else:
            stale = ~(self.keys[rows, agents] == keys).all(axis=1)
            if stale.any():
                self.values[rows[stale], agents[stale]] = np.nan
                self.keys[rows[stale], agents[stale]] = keys[stale]
            got = np.where(want, self.values[rows[:, None], agents[:, None], entries], np.nan)
            i, j = np.nonzero(want & np.isnan(got))
        if len(i):
            got[i, j] = measure(i, j)
            self.values[rows[i], agents[i], entries[i, j]] = got[i, j]
        return got
