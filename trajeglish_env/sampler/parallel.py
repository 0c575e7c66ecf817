"""Parallel decoding of the agents of a timestep by fixed-point (Jacobi) iteration, exact.

The trajeglish decoder makes the agents of a step sequential: agent ``a``'s input carries the token that
agent ``a - 1`` chose this step. Sequential decoding therefore costs one model call per sampled agent.
Every token, though, is a deterministic function of its inputs and of the agent's own counter-based
number (:func:`~trajeglish_env.sampler.sampling.counter_uniform`): the draw inverts the CDF of the
conditional at that number (the guard keeps it where allowed, else redraws the masked conditional with a
second number derived from it). So a whole run of agents can be decoded in one call from *drafted* tokens of
the agents before each one; where the drafts were right, the tokens are the ones sequential decoding
draws. A call is exact up to and including the first agent whose new token differs from its draft (its
inputs were all right); the agents after it are decoded again from the new tokens, which become their
drafts. The result is bit for bit the sequential one, whatever the drafts (a position's numbers do not
depend on the call that decodes it: :meth:`~trajeglish_env.model.network.TrajeglishModel.decode_at`); good
drafts (an agent's token of the previous step) only make the iteration end sooner.

Drafts come from looking one step ahead: a call whose run of agents ends the step also decodes the
positions of the next step (their inputs guessed from this step's drafts), and draws from them, with the
next step's numbers, the drafts that step starts from (:func:`look_ahead_rows`). Most of them are right,
so a step of a scene whose agents are all NPCs costs about one model call. The look-ahead adds a step of
positions to every row of a call, and it saves a call only where every row's drafts hold, so it is only
taken for few rows whose subsets are mostly agents to draft (:func:`look_ahead_pays`). Without one, an
agent's draft is drawn from its distribution of the step before with its number of this step
(:func:`coupled_drafts`): where the distribution moved little, the same number inverts both to the same
token (its token of the step before, drawn with another number, agrees less often); an agent without one
drafts its token of the step before.

A model that reads its step's states (neighbours, the road: ``ModelConfig.reads_states``) reads, at a
look-ahead position, the next step's states as the drafts give them (:func:`drafted_next_step`): where
the drafts hold they are the states sequential decoding reads there, and a look-ahead only drafts anyway.

Guarded sampling (:mod:`~trajeglish_env.sampler.guard`) reads, for each agent, the next states of the
agents that moved before it: in a parallel call those are the drafted states of its predecessors in the
run, which :func:`guard_view` supplies per agent. A draft drawn from the model alone misses wherever the
guard changes the draw (a stalled car pushed off, a follower capped, a wrong-way turn masked), and each miss
cuts the run short: so a call guards every pair it samples, so that the pairs after a miss are drafted anew
from guarded draws, and in a batch of few rows (:data:`GUARD_DRAFTS_MAX_ROWS`) the drafts a step starts from
are guarded too (:func:`guard_drafts`: the guard applied to the logits each draft was drawn from, with the
drafted states of the agents before it). On the bench's four SUMO scenes with every guard rule on, the AEC
env's step took 1.88 model calls before, 1.14 now.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np
import torch

from trajeglish_env.compiled import pair_compiled
from trajeglish_env.geometry import to_global
from trajeglish_env.sampler.rows import RowStates
from trajeglish_env.sampler.sampling import counter_uniform, draft_draws

if TYPE_CHECKING:
    from trajeglish_env.sampler.guard import SamplingGuard

# Stepping rows up to which the drafts a step starts from are guarded (:func:`guard_drafts`). A guarded
# draft saves a call only where every row's drafts hold, and costs a guard pass over every agent: measured
# with one thread (stop 83, the env's 24-agent scenes, alternately with and without it), the AEC env 11 %
# faster with it, B = 8 15 %, B = 32 6 % slower, B = 128 even; 16 and 32 rollouts of the 50-agent WOMD
# scene 3 % slower.
GUARD_DRAFTS_MAX_ROWS = 8

# The look-ahead's budget of positions (stepping rows x agent slots) for subsets whose every slot is an agent
# to draft; a subset with fewer gets that share of it (:func:`look_ahead_pays`).
LOOK_AHEAD_MAX_POSITIONS = 256


def previous_tokens(rs: RowStates) -> np.ndarray:
    """Drafts ``[B,N]`` for the step each row is at: each agent's token of the step before (-1: none)."""
    t = np.maximum(rs.now - 1, 0)
    r = np.arange(rs.B)[:, None]
    tok = rs.tokens[r, :, t[:, None]][:, 0] if rs.tokens.shape[2] else np.full((rs.B, rs.N), -1)
    ok = rs.known[r, :, t[:, None]][:, 0] & (rs.now > 0)[:, None]
    return np.where(ok, tok, -1)


def coupled_drafts(
    rs: RowStates,
    logits: np.ndarray,
    drawn_at: np.ndarray,
    temperature: float,
    top_p: float,
    wanted: np.ndarray | None = None,
) -> np.ndarray:
    """Drafts ``[B,N]`` for the step each row is at (-1: none): where an agent's token of the step before
    was drawn (in parallel) from class logits ``logits [B,N,V]`` (``drawn_at [B,N]``: the step of the
    draw), the draw of those logits at its number of this step; only where ``wanted [B,N]`` (default:
    everywhere; each agent's draw reads its own logits and number only)."""
    out = np.full((rs.B, rs.N), -1, np.int64)
    drawn = (drawn_at == (rs.now - 1)[:, None]) & (rs.now > 0)[:, None]
    rr, aa = np.nonzero(drawn if wanted is None else drawn & wanted)
    if len(rr):
        u = counter_uniform(rs.seed[rr], rs.now[rr], aa)
        out[rr, aa] = draft_draws(logits[rr, aa], temperature, top_p, u)  # a copy: drawn in place
    return out


def look_ahead_pays(rows: int, agents: int, sampled: int) -> bool:
    """Whether the chunks that end a step of a subset rank look one step ahead: ``rows`` stepping rows of
    ``agents`` slots hold ``sampled`` agents that the rank samples (whose drafts the look-ahead draws). It
    costs ``rows x agents`` positions whatever they hold, and saves a call of the next step only where every
    row's drafts hold, so the positions may be at most :data:`LOOK_AHEAD_MAX_POSITIONS` times the share of
    slots it drafts. Measured with one thread (stop 61; drafts never change a token), the look-ahead taken
    everywhere against nowhere: 24-agent env scenes (23 to draft) 17 % faster with it at B = 1, 18 % at 2,
    7 % at 4, even at 8; the 50-agent WOMD scene (6 subsets: the first drafts 21-24 agents, the others 2-8)
    4 % faster with one rollout, even with 2, 19 % slower with 4 and 8, and with 16 25 % slower (5 % when
    taken in follow-up calls only, the rule before); bundled scenes of 5-12 agents 9 % slower with 4
    rollouts, 24 % with 8."""
    positions = rows * agents
    return positions > 0 and positions * positions <= LOOK_AHEAD_MAX_POSITIONS * sampled


def kept_every_draft(
    rr: np.ndarray, rr_c: np.ndarray, tokens: np.ndarray, draft: np.ndarray, rows: int
) -> np.ndarray:
    """``[rows]`` rows of a parallel call whose every sampled pair (rows ``rr``) was checked (``rr_c``: the
    pairs the guard saw, all of them without it) and kept its draft (``tokens`` drawn, ``draft`` carried):
    every position of their chunk is then exact, the known ones after the last pair too (their inputs are
    decided tokens), so the whole chunk is decided, not only up to its last pair."""
    pairs = np.bincount(rr, minlength=rows)
    checked = np.bincount(rr_c, minlength=rows)
    missed = np.bincount(rr_c[tokens != draft], minlength=rows)
    return (pairs > 0) & (checked == pairs) & (missed == 0)


def look_ahead_rows(
    count: np.ndarray,
    slot: np.ndarray,
    tau: np.ndarray,
    now: np.ndarray,
    end: np.ndarray,
    agents: int,
    steps: int,
) -> np.ndarray:
    """``[B]`` rows whose chunk of ``count`` positions from slot ``slot`` ends their step at window step
    ``tau`` and whose window (``steps`` model steps) and rollout (``end``) hold the next step."""
    return (count > 0) & (slot + count == agents) & (tau + 1 < steps) & (now + 1 < end)


def draft_states(rs: RowStates, rows: np.ndarray, agents: np.ndarray, draft: np.ndarray) -> np.ndarray:
    """Next states ``[n,3]`` the drafted tokens ``draft [n]`` (>= 0) give agents ``agents`` of ``rows``."""
    t = rs.now[rows]
    return to_global(rs.mxyh[rows, agents, t], rs.vocab.templates[rs.kind[rows, agents], draft])


@contextmanager
def drafted_next_step(rs: RowStates, rows: np.ndarray, slots: np.ndarray) -> Iterator[None]:
    """While open, the model's next states (step ``now + 1``) of the window agents ``slots [r,A]`` (-1:
    none) of ``rows [r]`` whose token of this step is not decided yet are those their drafts
    (``rs._draft``) give, or their states now where they have none; on leaving, the states are put back
    (the decoded tokens set them). What a look-ahead position of a state-reading model reads."""
    if not len(rows):
        yield
        return
    r, j = np.nonzero(slots >= 0)
    rr, aa = rows[r], slots[r, j]
    t = rs.now[rr]
    pick = ~rs.known[rr, aa, t] & rs.valid[rr, aa, t] & (t + 1 < rs.T)
    rr, aa, t = rr[pick], aa[pick], t[pick]
    assert rs._draft is not None
    draft = rs._draft[rr, aa]
    saved = rs.mxyh[rr, aa, t + 1].copy(), rs.valid[rr, aa, t + 1].copy()
    nxt = rs.mxyh[rr, aa, t].copy()
    has = draft >= 0
    nxt[has] = draft_states(rs, rr[has], aa[has], draft[has])
    rs.mxyh[rr, aa, t + 1], rs.valid[rr, aa, t + 1] = nxt, True
    try:
        yield
    finally:
        rs.mxyh[rr, aa, t + 1], rs.valid[rr, aa, t + 1] = saved


def guard_view(
    rs: RowStates, rr: np.ndarray, who: np.ndarray, draft: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """What the guard sees of each pair ``(rr, who)`` of a parallel call (pairs sorted by row, then acting
    order): ``moved [n,N]``, the agents that moved before it (those its guard saw moved when the call
    began, :meth:`~trajeglish_env.sampler.rows.RowStates.guard_moved`, and its drafted predecessors in the
    call), and ``after [n,N,3]``, their next states (drafted ones for the predecessors). ``draft [n]``: the
    drafts the call's inputs carried (-1: none, i.e. not moved)."""
    n, N = len(rr), rs.N
    kernels = pair_compiled()
    if kernels is not None:  # the same view, compiled (pair_kernels.guard_view)
        moved, after, states = np.empty((n, N), bool), np.empty((n, N, 3)), np.zeros((n, 3))
        some = np.flatnonzero(draft >= 0)
        states[some] = draft_states(rs, rr[some], who[some], draft[some])
        flags = (rs.known, rs.acting_rank, rs.row_controlled, rs.row_external, rs.xyh, rs.now)
        pairs = (rr.astype(np.int64), who.astype(np.int64), draft.astype(np.int64))
        kernels.guard_view(*flags, *pairs, states, moved, after)
        return moved, after
    t = rs.now[rr]
    moved = rs.guard_moved(rr, who, t)
    after = rs.xyh[rr, :, t + 1].copy()
    drafted = np.flatnonzero(draft >= 0)
    if not len(drafted):
        return moved, after
    # pair q moves before pair p when both are of one row and q comes first: per row and agent, the first
    # pair that drafts it (n: none), before p or not
    starts = np.r_[True, rr[1:] != rr[:-1]]  # the pairs are sorted by row: each row's block of them
    rows, inverse = rr[starts], np.cumsum(starts) - 1
    first = np.full((len(rows), N), n)
    np.minimum.at(first, (inverse[drafted], who[drafted]), drafted)
    moved |= first[inverse] < np.arange(n)[:, None]
    # each row's drafted next states, read by the pairs of that row (only where they count as moved)
    row_after = rs.xyh[rows, :, rs.now[rows] + 1].copy()
    row_after[inverse[drafted], who[drafted]] = draft_states(rs, rr[drafted], who[drafted], draft[drafted])
    after = np.where(moved[..., None], row_after[inverse], after)
    return moved, after


def accepted(rr: np.ndarray, cc: np.ndarray, tokens: np.ndarray, draft: np.ndarray, rows: int) -> np.ndarray:
    """Per row, the chunk offset ``[rows]`` of the last exact pair of a parallel call (pairs ``rr``/``cc``
    sorted by row then offset; ``tokens`` drawn, ``draft`` carried): its first pair whose token differs from
    its draft, or its last pair when none does (-1: the row sampled nothing in the call)."""
    last = np.full(rows, -1)
    np.maximum.at(last, rr, cc)
    differ = tokens != draft
    first_miss = np.full(rows, np.iinfo(np.int64).max)
    np.minimum.at(first_miss, rr[differ], cc[differ])
    return np.where(first_miss < np.iinfo(np.int64).max, first_miss, last)


def guard_drafts(
    rs: RowStates,
    guard: SamplingGuard,
    stepping: np.ndarray,
    logits: np.ndarray,
    has_logits: np.ndarray,
    temperature: float,
    top_p: float,
) -> None:
    """Guard the drafts ``rs._draft [B,N]`` of the step the ``stepping [B]`` rows begin: each draft drawn
    from class logits ``logits [B,N,V]`` (``has_logits [B,N]``: those with them; the others keep theirs)
    becomes the guard's draw from those logits at the agent's number of this step, the agents before it in
    the acting order counting as moved to their drafted states. Only the drafts change (the guard's
    counters do not), so what is sampled stays exact whatever they are."""
    draft = rs._draft
    assert draft is not None
    t = np.minimum(rs.now, rs.T - 2)
    r_ix = np.arange(rs.B)[:, None]
    todo = stepping[:, None] & rs.row_controlled & (draft >= 0)
    todo &= ~rs.known[r_ix, :, t[:, None]][:, 0] & rs.valid[r_ix, :, t[:, None]][:, 0]
    pick = todo & has_logits
    if not pick.any():
        return
    rr, aa = np.nonzero(todo)  # every drafted agent of the step, in acting order per row (guard_view)
    order = np.lexsort((rs.acting_rank[rr, aa], rr))
    rr, aa = rr[order], aa[order]
    moved, after = guard_view(rs, rr, aa, draft[rr, aa])
    sel = np.flatnonzero(pick[rr, aa])
    rr, aa = rr[sel], aa[sel]
    u = counter_uniform(rs.seed[rr], rs.now[rr], aa)
    counters = dataclasses.replace(guard.stats)
    lg = torch.from_numpy(logits[rr, aa])
    draft[rr, aa] = guard.sample(rs, lg, rr, aa, rs.now[rr], u, temperature, top_p, (moved[sel], after[sel]))
    guard.stats = counters
