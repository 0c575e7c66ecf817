"""The guard's view of a step's pairs, kept from one guarded call to the next within the step.

Parallel decoding guards each agent of a step twice: once when the step's drafts are guarded
(:func:`~trajeglish_env.sampler.parallel.guard_drafts`), then when the model's call draws its token
(:func:`~trajeglish_env.sampler.parallel.guard_view`). Both calls see the agent at the same state, and where
its predecessors' drafts were not changed by the guard, they see the same agents moved to the same next
states, so its :class:`~trajeglish_env.sampler.guard_geometry.Pairs` row (neighbours, road rule, lights,
lanes, following cap, stall) is the same, number for number: every number of a pair depends on its own row
and view only. The memory keeps the last call's pairs with the views they were computed from, and a later
call of the same step takes the rows whose view matches (the moved agents, their next states, the states
valid at the next step) instead of computing them again. The engine clears it when a step begins, so a row
started anew never reads the rows of another scene."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from trajeglish_env.batch_geometry import latest_states

if TYPE_CHECKING:
    from trajeglish_env.sampler.guard_geometry import Pairs
    from trajeglish_env.sampler.rows import RowStates

# Pairs fields with one row per pair, and those of the near obstacles ``[n,K,...]`` (padded with these
# values where another call found fewer: ``near_real`` False keeps a padded obstacle out of every rule)
PER_PAIR = (
    "rows",
    "agents",
    "t",
    "origin",
    "size",
    "kind",
    "extent",
    "red",
    "depart",
    "pace",
    "stall",
    "keep_way",
    "follow_cap",
    "memo_keys",
)
NEAR_FILL = {"near_xyh": 0.0, "near_size": 1.0, "near_real": False, "near_escape": False}
EDGE_PER_PAIR = ("road", "limit", "maps", "rows")


def view_key(
    moved: np.ndarray, after: np.ndarray, valid_after: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a pair's numbers read of its view: which agents moved ``[n,N]``, the next states of those that
    moved and are present then ``[n,N,3]`` (zero elsewhere: never read there), and presence at the next
    step ``[n,N]``."""
    seen = moved & valid_after
    return moved, np.where(seen[..., None], after, 0.0), valid_after


def seen_states(
    rs: RowStates,
    rr: np.ndarray,
    who: np.ndarray,
    tt: np.ndarray,
    view: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every agent of rows ``rr`` as the guard of agents ``who`` at steps ``tt`` sees it: its latest decided
    state ``[n,N,3]`` (the next one where it moved this step), presence ``[n,N]``, velocity ``[n,N,2]`` (m a
    step, over the step that led there) and whether it moved ``[n,N]``; ``view``: which agents moved and
    their next states (default: as the rows say)."""
    t1, t0 = tt + 1, np.maximum(tt - 1, 0)
    now, valid_now, valid_after = rs.xyh[rr, :, tt], rs.valid[rr, :, tt], rs.valid[rr, :, t1]
    moved, after = (rs.guard_moved(rr, who, tt), rs.xyh[rr, :, t1]) if view is None else view
    before, valid_before = rs.xyh[rr, :, t0], rs.valid[rr, :, t0] & (tt >= 1)[:, None]
    state, present, velocity = latest_states(
        now, after, before, valid_now, valid_after, valid_before, moved, np.ones((len(rr), 1))
    )
    return state, present, velocity, moved


def stack_pairs(parts: list[tuple[Pairs, np.ndarray]], n: int) -> Pairs:
    """The pairs ``[n]`` whose rows at ``positions`` come from each ``(pairs, positions)`` of ``parts``
    (rows of :class:`~trajeglish_env.sampler.guard_geometry.Pairs`; the road cells and padded edges of the
    last part, the signals and lanes of all)."""
    first = parts[0][0]
    if len(parts) == 1 and np.array_equal(parts[0][1], np.arange(n)):
        return first
    fields: dict[str, object] = {}
    for name in PER_PAIR:
        sample = getattr(first, name)
        out = np.empty((n,) + sample.shape[1:], sample.dtype)
        for p, at in parts:
            out[at] = getattr(p, name)
        fields[name] = out
    k = max(p.near_xyh.shape[1] for p, _ in parts)
    for name, fill in NEAR_FILL.items():
        sample = getattr(first, name)
        out = np.full((n, k) + sample.shape[2:], fill, sample.dtype)
        for p, at in parts:
            got = getattr(p, name)
            out[at, : got.shape[1]] = got
        fields[name] = out
    last_edges = parts[-1][0].edges
    edge_fields = {}
    for name in EDGE_PER_PAIR:
        sample = getattr(last_edges, name)
        out = np.empty(n, sample.dtype)
        for p, at in parts:
            out[at] = getattr(p.edges, name)
        edge_fields[name] = out
    fields["edges"] = dataclasses.replace(last_edges, **edge_fields)
    fields["signals"] = {row: s for p, _ in parts for row, s in p.signals.items()}
    fields["lanes"] = {row: ld for p, _ in parts for row, ld in p.lanes.items()}
    return dataclasses.replace(first, **fields)  # type: ignore[arg-type]


def take_pairs(pairs: Pairs, idx: np.ndarray) -> Pairs:
    """Rows ``idx`` of ``pairs``."""
    fields: dict[str, object] = {name: getattr(pairs, name)[idx] for name in (*PER_PAIR, *NEAR_FILL)}
    edges = pairs.edges
    fields["edges"] = dataclasses.replace(edges, **{n: getattr(edges, n)[idx] for n in EDGE_PER_PAIR})
    return dataclasses.replace(pairs, **fields)  # type: ignore[arg-type]


class StepPairs:
    """The last guarded call's pairs of this step and the views they were computed from (see the module
    docstring)."""

    def __init__(self) -> None:
        self.pairs: Pairs | None = None
        self.key: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.slot = np.full((0, 0), -1, np.int64)  # [B,N]: each (row, agent)'s pair in ``pairs``, -1: none
        self.epoch = -1
        self.active = False  # whether calls keep and take pairs (the engine says, per step)

    def clear(self) -> None:
        """Forget every pair (a step begins)."""
        self.pairs = self.key = None

    def record(
        self, pairs: Pairs, key: tuple[np.ndarray, np.ndarray, np.ndarray], shape: tuple[int, int], epoch: int
    ) -> None:
        """Keep ``pairs`` (rows, agents ``[n]``) and their view ``key`` (:func:`view_key`), of rows ``shape =
        (B, N)`` and the road cells of ``epoch``."""
        self.pairs, self.key, self.epoch = pairs, key, epoch
        if self.slot.shape != shape:
            self.slot = np.full(shape, -1, np.int64)
        else:
            self.slot.fill(-1)
        self.slot[pairs.rows, pairs.agents] = np.arange(len(pairs.rows))

    def recall(
        self,
        rr: np.ndarray,
        who: np.ndarray,
        tt: np.ndarray,
        view: tuple[np.ndarray, np.ndarray],
        key: tuple[np.ndarray, np.ndarray, np.ndarray],
        shape: tuple[int, int],
        epoch: int,
        fresh: Callable[..., Pairs],
    ) -> tuple[Pairs, np.ndarray]:
        """The pairs ``(rr, who)`` at steps ``tt`` seen from ``view`` (its :func:`view_key` ``key``): those
        kept with the same view taken, the others computed by ``fresh(rr, who, tt, view)``; then kept in turn.
        Returns them and ``[n]`` which were taken."""
        at = self.match(rr, who, tt, key, shape, epoch)
        hits = at >= 0
        new, kept = np.flatnonzero(~hits), np.flatnonzero(hits)
        if not len(kept):
            pairs = fresh(rr, who, tt, view)
        else:
            assert self.pairs is not None
            old = take_pairs(self.pairs, at[kept])
            pairs = old
            if len(new):
                part = fresh(rr[new], who[new], tt[new], (view[0][new], view[1][new]))
                pairs = stack_pairs([(old, kept), (part, new)], len(rr))
        self.record(pairs, key, shape, epoch)
        return pairs, hits

    def match(
        self,
        rr: np.ndarray,
        who: np.ndarray,
        tt: np.ndarray,
        key: tuple[np.ndarray, np.ndarray, np.ndarray],
        shape: tuple[int, int],
        epoch: int,
    ) -> np.ndarray:
        """``[n]`` the kept pair of each ``(rr, who)`` at step ``tt`` with the same view ``key``, -1 where
        none is kept or its view differs."""
        n = len(rr)
        if self.pairs is None or self.key is None or self.slot.shape != shape or epoch != self.epoch:
            return np.full(n, -1, np.int64)
        at = self.slot[rr, who]
        ok = at >= 0
        if not ok.any():
            return at
        q = np.flatnonzero(ok)
        old = at[q]
        ok[q] &= self.pairs.t[old] == tt[q]
        moved, after, valid_after = key
        kept_moved, kept_after, kept_valid = self.key
        ok[q] &= (moved[q] == kept_moved[old]).all(axis=1) & (valid_after[q] == kept_valid[old]).all(axis=1)
        ok[q] &= (after[q] == kept_after[old]).all(axis=(1, 2))
        return np.where(ok, at, -1)


class StepDraws:
    """Per (row, agent), the model's draw its last guarded call of this step checked and whether the guard
    let it stand on the pair's geometry alone (no rule could mask it, or the draw broke none:
    :meth:`~trajeglish_env.sampler.guard.SamplingGuard._draw_allowed`). A later call whose pair has the same
    view (:class:`StepPairs`) and draws the same token keeps it without checking again: the check reads
    nothing but the pair and the token."""

    def __init__(self) -> None:
        self.plain = np.full((0, 0), -1, np.int64)
        self.stood = np.zeros((0, 0), bool)

    def kept(self, rr: np.ndarray, who: np.ndarray, tokens: np.ndarray, hits: np.ndarray) -> np.ndarray:
        """``[n]`` the pairs (``hits``: same view as the last call's) whose draw ``tokens`` stood then."""
        if not hits.any() or self.plain.shape[0] <= rr.max(initial=-1) or self.plain.shape[1] <= who.max():
            return np.zeros(len(rr), bool)
        return hits & (self.plain[rr, who] == tokens) & self.stood[rr, who]

    def record(
        self, rr: np.ndarray, who: np.ndarray, tokens: np.ndarray, stood: np.ndarray, shape: tuple[int, int]
    ) -> None:
        """Keep the draws ``tokens [n]`` of pairs ``(rr, who)`` and whether they stood (rows ``shape``)."""
        if self.plain.shape != shape:
            self.plain, self.stood = np.full(shape, -1, np.int64), np.zeros(shape, bool)
        self.plain[rr, who], self.stood[rr, who] = tokens, stood
