"""Guarded sampling (``SamplingConfig.guard``): candidate tokens that would overlap another agent, take a
vehicle or cyclist off the road or across a red stop line, or leave it standing at a green one, are masked
before a token is drawn.

The intra-timestep factorization makes this exact: when an agent is sampled, the next states of the agents
that moved before it in the step are known (and the current boxes of those that have not moved yet,
logged agents acting after it among them: the guard sees no more of the log than the order shows), so
each of its candidate tokens -- every template of its class, applied to its current model state -- can be
checked against them (:mod:`~trajeglish_env.sampler.guard_geometry`). A candidate is masked when its box
overlaps one of those boxes, or, for a vehicle or cyclist, when a corner of its box lies more than the
env's off-road margin beyond a road edge, or when it breaks a signal rule
(:mod:`~trajeglish_env.sampler.guard_signals`). With the road ahead
(:mod:`~trajeglish_env.sampler.guard_ahead`) a vehicle's moving candidates whose kept-up motion stays on the
road a shorter way than another allowed one's are masked too, and so are the candidates whose forward step
differs from the agent's last one by more than ``SamplingConfig.guard_step_change`` (a redraw from a
masked distribution could otherwise stop a car dead from 20 m/s: 35 of 948 guarded vehicle-rollouts of the
bundled and WOMD scenes before it). When every candidate is masked, the speed-change rule widens to the
gentlest change the other rules leave (a car brakes as little as the road allows), then the escape
obstacles are dropped, then the map rules; when that still leaves none, the token is drawn unguarded.

The token keeps the model's own draw where the rules allow it: the draw of
:func:`~trajeglish_env.sampler.sampling.sample_with_uniform` with the agent's counter-based number ``u`` (so a
row's rollout never depends on the other rows) is checked first, and only where it breaks a rule is the token
drawn from the masked logits, with a second number of the agent's
(:func:`~trajeglish_env.sampler.sampling.second_uniform`). This is exactly the masked distribution (a token
the rules allow comes out with probability p + (1 - Z) p / Z = p / Z, Z the allowed mass), and it changes no
draw the rules allow: a vehicle keeps the model's speed where masked mass elsewhere would have shifted the
inverted number onto a neighbouring token, and the drafts of parallel decoding (the unguarded draws) stay
right (:mod:`~trajeglish_env.sampler.parallel`). Under a nucleus (top_p < 1) the masked logits are drawn at
``u`` (a nucleus of the masked logits is not a coupling of the unmasked draw); at temperature 0 the token is
the most likely allowed one.

Checking all V candidates of every agent would cost more than the model, so (with top_p = 1, or at
temperature 0) the draw itself is checked first, then the 6 most likely candidates (LAZY_CANDIDATES): the
masses of the allowed ones and of the unchecked rest bound the cumulative distribution of every possible
mask, and when those bounds put the redraw on the same token, that token is the one the full mask gives (at
temperature 0: the most likely allowed one, when one of them is allowed; a checked candidate whose
road-ahead verdict turns on unchecked ones counts as unchecked). The other agents (when the redraw falls near
a token boundary, or when most of the likely candidates are masked) are checked with 24, then 96 (then 384
in a larger vocabulary), then all; a pass whose candidates hold less than half the probability (an untrained
model) is skipped. With no lazy passes (LAZY_CANDIDATES empty) every candidate of every agent is checked,
the draw itself too (the reference the tests compare with)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from trajeglish_env.sampler.guard_ahead import AHEAD_CHECKS, ahead_masks, ahead_of_all
from trajeglish_env.sampler.guard_geometry import GuardGeometry, Pairs
from trajeglish_env.sampler.guard_signals import DEPART_STEP
from trajeglish_env.sampler.guard_stall import frozen
from trajeglish_env.sampler.pair_memo import StepDraws
from trajeglish_env.sampler.rows import RowStates
from trajeglish_env.sampler.sampling import (
    draw_tables,
    sample_from_cdf,
    sample_from_probs,
    sample_with_uniform,
    second_uniform,
    token_probs,
)

# the most likely candidates checked first, then more where the draw is not decided yet, then all: the
# shipped model's draws are mostly decided by 6 (the check's cost grows with the candidates; 16, 64 before:
# 32 rollouts x 20 steps of the shared WOMD scene took 31.2 s, now 23.6 s, the same tokens); a pass is
# made only with fewer candidates than the vocabulary has (an extended one of 2048 gets the fourth)
LAZY_CANDIDATES = (6, 24, 96, 384)
LAZY_MIN_MASS = 0.5  # a lazy pass is tried where its candidates hold at least this probability mass
_SLACK = 1e-12  # probability mass of slack in the bounds, covering the rounding of the full draw's CDF


@dataclass
class GuardStats:
    """Counters of a guard: ``sampled`` agents, ``guarded`` ones (an obstacle or a road edge within reach
    of a candidate), ``full`` ones whose V candidates were all checked, ``masked`` draws that differ from
    the unguarded one, and fallbacks that dropped the agents to escape (``escape_fallback``), the
    speed-change rule (``step_fallback``), the road-edge rule (``edge_fallback``) or the whole guard
    (``plain_fallback``)."""

    sampled: int = 0
    guarded: int = 0
    full: int = 0
    masked: int = 0
    escape_fallback: int = 0
    step_fallback: int = 0
    edge_fallback: int = 0
    plain_fallback: int = 0


@dataclass
class SamplingGuard:
    """The guard of one engine (see the module docstring): its geometry and counters."""

    geometry: GuardGeometry
    stats: GuardStats = field(default_factory=GuardStats)
    draws: StepDraws = field(default_factory=StepDraws)

    def sample(
        self,
        rs: RowStates,
        logits: torch.Tensor,
        rows: np.ndarray,
        agents: np.ndarray,
        t: np.ndarray,
        uniform: np.ndarray,
        temperature: float,
        top_p: float,
        view: tuple[np.ndarray, np.ndarray] | None = None,
        drawn: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> np.ndarray:
        """Tokens ``[n]`` of agents ``agents`` of rows ``rows`` at steps ``t`` from their class logits
        ``[n,V]`` and numbers ``uniform [n]``: the draw of the guarded logits. ``view``: per pair, the
        agents that moved before it ``[n,N]`` and their next states ``[n,N,3]`` (default: the rows'
        state, i.e. one pair per row, as in sequential decoding; :func:`~trajeglish_env.sampler.parallel.
        guard_view` for a parallel call). ``drawn``: the pairs' :func:`draw_tables` when the caller made
        them already (a parallel call draws every position unguarded first)."""
        lazy = temperature == 0 or top_p == 1.0  # a masked nucleus depends on every candidate
        probs = cdf = None  # the draw's probabilities and CDF, shared by the lazy passes
        if temperature == 0:
            tokens = logits.argmax(-1).numpy()
        elif lazy:
            probs, cdf = draw_tables(logits, temperature) if drawn is None else drawn
            tokens = sample_from_cdf(cdf, uniform)
        else:
            tokens = sample_from_probs(token_probs(logits, temperature), top_p, uniform)
        pairs, hits = self.geometry.recall(rs, rows, agents, t, view)
        # a pair seen from the same view earlier in the step keeps a draw that stood then (not a stalled
        # rider: whether its stall rule holds reads the logits)
        stood = self.draws.kept(rows, agents, tokens, hits & ~pairs.stall)
        if pairs.stall.any():  # a stalled rider is pushed only where the model has frozen
            pairs = self._frozen_stalls(pairs, logits, temperature, probs)
        every = np.arange(len(rows))  # a draw that jumps in speed is guarded with nothing else near
        flagged = pairs.guarded | self.geometry.jumps(pairs, every, tokens[:, None])[:, 0]
        guarded = np.flatnonzero(flagged & ~stood)
        self.stats.sampled += len(rows)
        self.stats.guarded += int(flagged.sum())
        shape = (rs.B, rs.N)
        if not len(guarded):
            self.draws.record(rows, agents, tokens, ~flagged | stood, shape)
            return tokens
        plain = tokens[guarded]
        sub = logits[torch.from_numpy(guarded)]
        at = torch.from_numpy(guarded)
        sub_probs = None if probs is None else probs[at].numpy()
        sub_cdf = None if cdf is None else cdf[at].numpy()
        chosen, done = plain.copy(), np.zeros(len(guarded), bool)
        passes = [k for k in LAZY_CANDIDATES if k < logits.shape[1]] if lazy else []
        keep = temperature > 0 and lazy  # the model's draw stands where allowed; else a redraw at ``redraw``
        redraw = second_uniform(uniform) if keep else uniform
        beat = np.full(len(guarded), -2)  # a redraw stands where a checked candidate reaches farther
        if keep and passes:  # the draw itself first: most draws break no rule
            done, beat = self._draw_allowed(pairs, guarded, plain)
        stood[guarded] = done
        self.draws.record(rows, agents, tokens, ~flagged | stood, shape)
        for k in passes:
            rest = np.flatnonzero(~done)
            if not len(rest):
                break
            sel = guarded[rest]
            if sub_probs is None or sub_cdf is None:
                chosen[rest], done[rest] = self._lazy_argmax(pairs, sel, sub[torch.from_numpy(rest)], k)
            else:
                chosen[rest], done[rest] = self._lazy_draw(
                    pairs, sel, sub_probs[rest], sub_cdf[rest], k, redraw[sel], beat[rest]
                )
        rest = np.flatnonzero(~done)
        if len(rest):
            chosen[rest] = self._full_draw(
                pairs,
                guarded[rest],
                sub[torch.from_numpy(rest)],
                temperature,
                top_p,
                redraw[guarded[rest]],
                plain[rest] if keep else None,
            )
        tokens[guarded] = chosen
        self.stats.full += len(rest)
        self.stats.masked += int((chosen != plain).sum())
        return tokens

    def _frozen_stalls(
        self, pairs: Pairs, logits: torch.Tensor, temperature: float, probs: torch.Tensor | None
    ) -> Pairs:
        """``pairs`` whose stall flags of standing riders hold only where the model's probability of moving
        is under :data:`~trajeglish_env.sampler.guard_stall.FROZEN_MASS` (a rider already departing keeps
        its flag through the departure)."""
        q = np.flatnonzero(pairs.stall & ~(pairs.pace >= DEPART_STEP))
        if not len(q):
            return pairs
        at = torch.from_numpy(q)
        if temperature <= 0:  # the argmax: all the mass on one token
            p = torch.nn.functional.one_hot(logits[at].argmax(-1), logits.shape[1]).double()
        else:
            p = probs[at] if probs is not None else token_probs(logits[at], temperature)
        step = self.geometry.templates[pairs.kind[q, None], np.arange(logits.shape[1])[None], 0]
        stall = pairs.stall.copy()
        stall[q] = frozen(p.numpy(), step >= DEPART_STEP)
        return dataclasses.replace(pairs, stall=stall)

    def _draw_allowed(self, pairs: Pairs, sel: np.ndarray, draw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For pairs ``sel [m]`` and the model's draws ``draw [m]``: ``[m]`` draws every rule allows for sure
        (nothing is masked then but what the draw does not take), and ``[m]`` the reach a checked candidate
        must pass for the full mask to mask the draw: -2 (none) where the draw breaks a one-step rule (with
        any candidate allowed, the full mask masks it too), the draw's own reach where it is allowed by the
        one-step rules but short of the road ahead's full reach (*unsure*: a candidate reaching farther
        masks it, else it stands)."""
        collide, escape, off, jump = self.geometry.blocked_parts(pairs, sel, draw[:, None])
        ok = ~(collide | escape | off | jump)
        beat = np.full(len(sel), -2)
        if self.geometry.road_ahead <= 0:
            return ok[:, 0], beat
        reach, look = self.geometry.reach(pairs, sel, draw[:, None], ok)
        unsure = (look & (reach < AHEAD_CHECKS))[:, 0]
        beat[unsure] = reach[unsure, 0]
        return ok[:, 0] & ~unsure, beat

    def _lazy_argmax(
        self, pairs: Pairs, sel: np.ndarray, logits: torch.Tensor, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Temperature 0: the most likely allowed candidate (lowest index on ties) when one of the ``k``
        most likely is allowed."""
        lg = logits.double().numpy()
        k = min(k, lg.shape[1])
        order = np.argsort(-lg, axis=1, kind="stable")[:, :k]
        collide, off = self.geometry.blocked(pairs, sel, order)
        ok = ~(collide | off)
        first = np.argmax(ok, axis=1)
        r = np.arange(len(sel))
        done = ok.any(axis=1)
        if self.geometry.road_ahead > 0:  # decided where no unsure candidate comes before the first
            masked, unsure = ahead_masks(*self.geometry.reach(pairs, sel, order, ok))
            sure = ok & ~masked & ~unsure
            first = np.argmax(sure, axis=1)
            done = sure.any(axis=1) & ~(unsure & (np.arange(k) < first[:, None])).any(axis=1)
        return order[r, first], done

    def _lazy_draw(
        self,
        pairs: Pairs,
        sel: np.ndarray,
        probs: np.ndarray,
        cdf: np.ndarray,
        k: int,
        uniform: np.ndarray,
        beat: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The draw of the fully masked distribution (``probs [m,V]``: :func:`token_probs` of the pairs,
        ``cdf [m,V]`` their cumulative sums) where the ``k`` most likely candidates decide it (see the module
        docstring); ``done [m]`` says where. Beyond choosing the candidates, O(k) a pair: the bounds at a
        token are read from the CDF and the checked candidates (no V-sized pass). ``beat [m]``: decided
        only where a checked candidate reaches farther than this (the model's own draw, unsure, is then
        masked; see :meth:`_draw_allowed`)."""
        m, v = probs.shape
        k = min(k, v)
        top = np.argpartition(-probs, k - 1, axis=1)[:, :k]
        rows = np.arange(m)[:, None]
        chosen, done = np.zeros(m, np.int64), np.zeros(m, bool)
        mass = probs[rows, top]
        try_ = np.flatnonzero(mass.sum(axis=1) >= LAZY_MIN_MASS)  # else the bounds are too loose
        if not len(try_):
            return chosen, done
        top, mass, cdf, uniform = top[try_], mass[try_], cdf[try_], uniform[try_]
        collide, off = self.geometry.blocked(pairs, sel[try_], top)
        ok = ~(collide | off)
        unsure = np.zeros_like(ok)
        farthest = np.full(len(try_), -1)
        if self.geometry.road_ahead > 0:  # unsure: the road-ahead rule waits on unchecked candidates
            reach, look = self.geometry.reach(pairs, sel[try_], top, ok)
            masked, unsure = ahead_masks(reach, look)
            farthest = np.where(look, reach, -1).max(axis=1, initial=-1)
            ok &= ~masked & ~unsure
        order = np.argsort(top, axis=1)  # the checked candidates in token order
        top, mass = np.take_along_axis(top, order, 1), np.take_along_axis(mass, order, 1)
        ok, unsure = np.take_along_axis(ok, order, 1), np.take_along_axis(unsure, order, 1)
        sure = np.where(ok, mass, 0.0)
        z = sure.sum(axis=1)  # allowed for sure; eps: unchecked or unsure, either way
        eps = np.maximum(cdf[:, -1] - mass.sum(axis=1), 0.0) + np.where(unsure, mass, 0.0).sum(axis=1)
        # the masked draw's token is at most the first allowed candidate whose allowed mass up to it beats
        # the largest threshold (``latest``) ...
        past = np.cumsum(sure, axis=1) > (uniform * (z + eps) + _SLACK)[:, None]
        first = np.argmax(past, axis=1)
        r = np.arange(len(try_))
        latest = top[r, first]
        # ... and at least it when all the mass before it, less the candidates found blocked, stays under
        # the smallest one
        blocked_before = np.where(~ok & ~unsure & (top < latest[:, None]), mass, 0.0).sum(axis=1)
        before = np.where(latest > 0, cdf[r, np.maximum(latest - 1, 0)] - blocked_before, -np.inf)
        chosen[try_] = latest
        done[try_] = (z > 0) & past.any(axis=1) & (before <= uniform * z - _SLACK)
        if beat is not None:
            done[try_] &= farthest > beat[try_]
        return chosen, done

    def _full_draw(
        self,
        pairs: Pairs,
        sel: np.ndarray,
        logits: torch.Tensor,
        temperature: float,
        top_p: float,
        uniform: np.ndarray,
        keep: np.ndarray | None = None,
    ) -> np.ndarray:
        """Check every candidate of pairs ``sel`` and draw from the masked logits, with the fallbacks;
        ``keep [m]``: the model's draws, which stand where the final mask allows them."""
        v = logits.shape[1]
        every = np.broadcast_to(np.arange(v), (len(sel), v))
        collide, escape, off, jump = self.geometry.blocked_parts(pairs, sel, every)
        ok = ~(collide | escape | off | jump)
        if self.geometry.road_ahead > 0:
            ok &= ~ahead_of_all(*self.geometry.reach(pairs, sel, every, ok))
        leap = ~ok.any(axis=1)  # nothing left: the speed-change rule widens first, to the gentlest change
        if leap.any():  # the other rules leave (a car brakes as little as the road allows, not at random)
            rest = ~(collide | escape | off)[leap]
            if self.geometry.road_ahead > 0:
                rest &= ~ahead_of_all(*self.geometry.reach(pairs, sel[leap], every[leap], rest))
            change = self.geometry.step_changes(pairs, sel[leap], every[leap])
            least = np.where(rest, change, np.inf).min(axis=1, initial=np.inf)[:, None]
            ok[leap] = rest & (change <= np.maximum(least, 1.0) + 1e-9)
        self.stats.step_fallback += int((leap & ok.any(axis=1)).sum())
        trapped = ~ok.any(axis=1)  # no candidate escapes what moved into it: those agents are left out
        ok[trapped] = ~(collide | off)[trapped]
        self.stats.escape_fallback += int((trapped & ok.any(axis=1)).sum())
        no_edge = ~ok.any(axis=1)
        ok[no_edge] = ~collide[no_edge]
        nothing = ~ok.any(axis=1)
        ok[nothing] = True
        self.stats.edge_fallback += int((no_edge & ~nothing).sum())
        self.stats.plain_fallback += int(nothing.sum())
        masked = logits.masked_fill(torch.from_numpy(~ok), float("-inf"))
        drawn = sample_with_uniform(masked, temperature, top_p, uniform)
        if keep is None:
            return drawn
        return np.where(ok[np.arange(len(sel)), keep], keep, drawn)
