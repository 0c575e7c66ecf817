"""Closed-loop token simulation of many rows at once, with a spatial and temporal sliding window (paper
appendix "Extended rollouts").

A *row* is one rollout of one scene. :class:`BatchEngine` steps B rows in lockstep (one timestep per
call of :meth:`BatchEngine.advance`), each with its own scene, clock, window schedule and random stream,
and batches every model call across rows: the model is called once per token position of a step for
all B rows. Rows may (re)start at any step boundary (:meth:`BatchEngine.start_rows`), which is how the
vectorized environments reset one scene while the others go on. :class:`RolloutEngine` is the special
case of R rollouts of one scene.

Roles per agent: *controlled* (the model samples its tokens), *replay* (follows given motion known in
advance, e.g. the log) and *external* (its next state is supplied step by step from outside, e.g. by an
RL policy in the environment). Replay and external agents keep their exact states; the model sees their
motion tokenized from its own (tokenized) view of them, so errors never accumulate.

Windows: at recompute steps the active agents are covered by subsets (:mod:`subsets`); each subset is a
model context whose initial states are the agents' states ``prime`` steps earlier (or their first valid
state after that), and whose caches are primed with the tokens of those steps. Within a timestep the
subsets act in order; an agent acts (is sampled) in the first subset holding it and is forced in later
ones. Subset ``k`` of every row is one model batch; rows may be at different points of their windows.

Reproducibility: a row's tokens depend only on its scene, settings and seed, never on the other rows of
the batch: draws are counter-based (:func:`~trajeglish_env.sampler.sampling.counter_uniform` of the row seed,
the step and the agent) and inference is batch-invariant (:mod:`trajeglish_env.model.layers`).

Layers of the engine: :mod:`~trajeglish_env.sampler.rows` (per-row state: starting rows, supplying
external agents, handing entering agents to the model) <- :mod:`~trajeglish_env.sampler.windows` (building
and priming the model contexts) <- this module (stepping: decoding and sampling the positions of each
step, each row with its own cursor through the agent subsets).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.geometry import to_global
from trajeglish_env.heap import keep_freed_memory
from trajeglish_env.model.config import Variant
from trajeglish_env.model.layers import MIN_GEMM_ROWS, linear_compute
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.parallel import (
    GUARD_DRAFTS_MAX_ROWS,
    accepted,
    coupled_drafts,
    drafted_next_step,
    guard_drafts,
    guard_view,
    kept_every_draft,
    look_ahead_pays,
    look_ahead_rows,
    previous_tokens,
)
from trajeglish_env.sampler.rows import RowSpec
from trajeglish_env.sampler.sampling import (
    counter_uniform,
    draft_draws,
    draw_tables,
    sample_from_cdf,
    sample_with_uniform,
    stream_seed,
)
from trajeglish_env.sampler.windows import Window, WindowedRows
from trajeglish_env.sampler.windows import _row_blocks as _row_blocks  # re-exported
from trajeglish_env.scenario import Scenario

if TYPE_CHECKING:
    from trajeglish_env.sampler.guard import SamplingGuard


class BatchEngine(WindowedRows):
    """Steps ``rows`` independent rows in lockstep (see the module docstring).

    Per-row state (padded to the largest scene: ``N`` agents, ``T`` steps): exact states ``xyh [B,N,T,3]``
    and ``valid [B,N,T]``; the model's tokenized view ``mxyh``; ``tokens [B,N,T-1]`` and ``known`` (the
    token of a step is decided); ``now [B]`` the step being played and ``end [B]`` the last step.
    ``cache_dtype``: dtype of the self-attention caches (None: ``config.cache_dtype``).
    """

    def __init__(
        self,
        ckpt: Checkpoint,
        rows: int,
        config: SamplingConfig | None = None,
        cache_dtype: torch.dtype | None = None,
    ):
        if rows < 1:
            raise ValueError(f"rows must be >= 1, got {rows}")
        keep_freed_memory()  # a step's activations reuse freed heap memory (trajeglish_env/heap.py)
        config = config or SamplingConfig()
        cache_dtype = config.torch_cache_dtype if cache_dtype is None else cache_dtype
        model = ckpt.model.eval()
        steps = model.cfg.steps
        every, prime = config.every(steps), config.prime(steps)
        super().__init__(model, ckpt.vocabulary, rows, prime, every, config.subsets, cache_dtype)
        self.config = config
        self._compute_dtype = config.torch_compute_dtype(self.device, rows)
        self._rank = np.zeros(self.B, dtype=np.int64)  # per row: the subset rank it decodes in this step
        self._ahead_ok = (-1, False)  # (rank, whether its chunks that end the step look ahead: parallel.py)
        self.guard: SamplingGuard | None = None
        if config.guard:  # guarded sampling (its geometry needs the rows' road edges)
            from trajeglish_env.sampler.guard import SamplingGuard
            from trajeglish_env.sampler.guard_geometry import GuardGeometry

            self.guard = SamplingGuard(GuardGeometry.of(self.vocab.templates, config))
            self.with_edges = True
        self._slot = np.zeros(self.B, dtype=np.int64)  # per row: next slot of that rank to decode
        self.model_calls = 0  # decoding calls made (a measure of the cost of a step)
        self.look_ahead_calls = 0  # of them, calls that also decoded the next step (parallel.look_ahead_pays)

    # ------------------------------------------------------------------ stepping
    def advance(self) -> tuple[np.ndarray, np.ndarray] | None:
        """See :meth:`_advance`."""
        return self._advance()

    def _advance(self) -> tuple[np.ndarray, np.ndarray] | None:
        """:meth:`_advance_step`, the model's linear layers multiplying in ``config.compute_dtype``, under
        ``torch.inference_mode`` (no autograd bookkeeping of the many small ops and views a step makes: the
        same kernels and numbers, a single env's step 1.12x faster than under ``no_grad``, stop 88)."""
        with torch.inference_mode(), linear_compute(self._compute_dtype):
            return self._advance_step()

    def _advance_step(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Act the positions of the current step in order, for every stepping row. Returns
        ``(rows, agents)``: external agents whose next states are needed (supply them, then call again),
        or None when the step is complete (every stepping row is one step further). A waiting row holds
        while the others go on, so the call returns once no row can go further without a supply: every
        row then stands at its next external agent (inference is batch-invariant, so the grouping of rows
        into calls never changes a token).

        Each row runs through the slots of subset rank 0, 1, ... with its own cursor: a model call decodes,
        per row, the run of positions up to its next *blocker* (an agent to sample, or an external agent
        not supplied yet) in one chunk, since the inputs of all of them are known. Known agents (forced,
        padding, supplied externals) therefore cost no extra calls. Decoding in parallel
        (:mod:`~trajeglish_env.sampler.parallel`), the chunk runs to the next external agent not supplied
        yet, and the cursor moves past the pairs the call decided exactly."""
        stepping = self.stepping
        if not stepping.any():
            raise RuntimeError("no row has steps left (start rows, or the horizon is reached)")
        self._tokenize_supplied()
        if not self._in_step:
            self._hand_over(np.flatnonzero(stepping & (self.now == self.handover_step)))
            arrived, entered = self._hand_over_entering(stepping)
            rebuild = self._needs_windows()
            late = ~rebuild[arrived]  # the agents that entered join a window of the rows not planned now
            if late.any():
                rebuild[self._admit(arrived[late], entered[late])] = True
            if rebuild.any():
                self._build_windows(np.flatnonzero(rebuild))
            self._in_step = True
            drafts_guarded = stepping.sum() <= GUARD_DRAFTS_MAX_ROWS and self.config.intra_step == "parallel"
            if self.guard is not None:
                self.guard.geometry.forget_step(remember=drafts_guarded)
            self._rank = np.zeros(self.B, dtype=np.int64)
            self._ahead_ok = (-1, False)
            self._slot = np.where(self.num_subsets > 0, 0, self.cfg.max_agents)
            self._draft = None
            if self.config.intra_step == "parallel":  # drafts: the look-ahead of the last step, else repeats
                ahead = self._ahead if self._ahead is not None else np.full((self.B, self.N), -1)
                coupled = self._coupled_drafts(ahead < 0)  # where the look-ahead drafted none
                self._draft = np.where(
                    ahead >= 0, ahead, np.where(coupled >= 0, coupled, previous_tokens(self))
                )
                if self.guard is not None and drafts_guarded:
                    self._guard_drafts(stepping, ahead >= 0, coupled >= 0)  # drafts as the guard draws
                self._ahead = np.full((self.B, self.N), -1)
                self._ahead_rank = np.full((self.B, self.N), np.iinfo(np.int64).max)
        A = self.cfg.max_agents
        ranks = int(self.num_subsets[stepping].max(initial=0))
        t_safe = np.minimum(self.now, self.T - 2)
        r_ix, b_ix = np.arange(self.B)[:, None], np.arange(self.B)
        slots = np.stack([w.slots for w in self.windows[:ranks]]) if ranks else np.zeros((0, self.B, A), int)
        while True:
            at = np.minimum(self._rank, max(ranks - 1, 0))
            row_slots = slots[at, b_ix] if ranks else np.full((self.B, A), -1)  # [B,A] each row's subset
            safe = np.maximum(row_slots, 0)
            undecided = (row_slots >= 0) & ~self.known[r_ix, safe, t_safe[:, None]] & stepping[:, None]
            wait = undecided & self.row_external[r_ix, safe] & self.valid[r_ix, safe, t_safe[:, None]]
            prev = np.clip(self._slot - 1, 0, A - 1)
            waiting = stepping & (self._rank < self.num_subsets) & (self._slot > 0) & wait[b_ix, prev]
            # a row through its subset goes on to its next one (or has acted in every subset)
            through = stepping & (self._slot >= A) & ~waiting & (self._rank < self.num_subsets)
            if through.any():
                self._rank[through] += 1
                self._slot[through] = np.where(self.num_subsets[through] > self._rank[through], 0, A)
                continue
            active = stepping & (self._slot < A) & ~waiting
            if not active.any():
                if waiting.any():  # no row can go on without a supply: hand the waiting ones out
                    rows = np.flatnonzero(waiting)
                    return rows, row_slots[rows, prev[rows]]
                break
            # the rows at the lowest subset rank that can go on decode together (the others wait for them)
            k = int(self._rank[active].min())
            w = self.windows[k]
            here = active & (self._rank == k)
            sample = undecided & self.row_controlled[r_ix, safe] & (self._rank == k)[:, None]
            if self._ahead_ok[0] != k:  # decided once per rank, from all the agents it samples
                n_rows = int((stepping & (self.num_subsets > k)).sum())
                k_slots = np.maximum(slots[k], 0)
                k_sample = (slots[k] >= 0) & ~self.known[r_ix, k_slots, t_safe[:, None]] & stepping[:, None]
                k_sample &= self.row_controlled[r_ix, k_slots]
                self._ahead_ok = (k, look_ahead_pays(n_rows, A, int(k_sample.sum())))
            if self.cfg.variant is not Variant.TRAJEGLISH:
                blocker = np.zeros_like(sample)
            else:
                blocker = wait if self._draft is not None else sample | wait
            blocker &= np.arange(A)[None] >= self._slot[:, None]
            stop = np.where(blocker.any(1), np.argmax(blocker, axis=1), A - 1)
            count = np.where(here, stop - self._slot + 1, 0)
            self._slot = self._slot + self._decode_chunk(w, count, sample, stepping, t_safe)
        late = self._pending_external(stepping, t_safe)
        if late is not None:
            return late
        rows = np.flatnonzero(stepping)
        self._delay_blocked_entries(rows)
        self.known[rows, :, self.now[rows]] = True  # undecided tokens are unobserved from now on
        self.now[rows] += 1
        self._in_step = False
        self._draft = None
        return None

    def _hand_over(self, rows: np.ndarray) -> None:
        """Where ``rows``' logs end, their logged agents still present become controlled: the model drives
        them from this step on (their windows are planned anew to hold them)."""
        for r in rows.tolist():
            agents = np.flatnonzero(self.handover[r] & self.valid[r, :, self.now[r]])
            if len(agents):
                t, end = int(self.now[r]), int(self.end[r])
                self.row_controlled[r, agents] = True
                self.known[r, agents, t:end] = False
                self.valid[r, agents, t + 1 : end + 1] = True
                self.window_step[r] = -1
            self.handover[r] = False

    def _decode_chunk(
        self, w: Window, count: np.ndarray, sample: np.ndarray, stepping: np.ndarray, t: np.ndarray
    ) -> np.ndarray:
        """Decode ``count[b]`` positions of window ``w`` from each row's cursor; sample the agents to
        sample among them. Returns how many positions of each row are decided (all ``count`` of them,
        but for a parallel call: up to its first drawn token that differs from its draft)."""
        A = self.cfg.max_agents
        tau = self.now - w.start
        ahead = np.zeros(self.B, bool)
        if self._draft is not None and self._ahead_ok[1]:
            # chunks that end the step look one step ahead (parallel.look_ahead_rows)
            ahead = look_ahead_rows(count, self._slot, tau, self.now, self.end, A, self.cfg.steps)
        extent = count + A * ahead
        n = max(1, int(extent.max()))  # a position's numbers do not depend on n (model.layers.MIN_QUERIES)
        if self._draft is not None:  # at least MIN_GEMM_ROWS rows x queries: the linear layers then take the
            # inputs as they are instead of padding each one (the same numbers: padding is never stored)
            n = max(n, -(-MIN_GEMM_ROWS // self.B))
        start = np.where(count > 0, tau * A + self._slot, 0)
        offsets = np.arange(n)
        inside = offsets[None] < count[:, None]
        decoded = offsets[None] < extent[:, None]
        positions = np.where(decoded, start[:, None] + offsets, start[:, None])
        carried, own = self._inputs(np.arange(self.B), w.slots, w.start, positions)
        if ahead.any():  # a look-ahead position carries its predecessor's token of this step instead
            guess = decoded & ~inside & (positions % A > 0)
            carried_now, _ = self._inputs(
                np.arange(self.B), w.slots, w.start, np.where(guess, positions - A, 0)
            )
            carried = torch.where(torch.from_numpy(guess).to(self.device), carried_now, carried)
        rows = np.flatnonzero(ahead) if self.cfg.reads_states else np.zeros(0, np.int64)
        with drafted_next_step(self, rows, w.slots[rows]):  # what look-ahead positions read
            view = self._view(np.arange(self.B), w.slots, w.start, positions, decoded)
        slots = positions % A
        todo = inside & np.take_along_axis(sample, slots, 1)
        read = self._read_span(todo | (decoded & ~inside & ahead[:, None]), n)
        hidden = self.model.decode_at(w.cache, w.agents, carried, own, start, extent, view, read)
        self.model_calls += 1
        self.look_ahead_calls += int(ahead.any())
        rr, cc = np.nonzero(todo)
        who = w.slots[rr, slots[rr, cc]]
        # the look-ahead's pairs and this step's take their class logits from one pass of the head
        none = (rr[:0],) * 4
        a_rr, a_cc, a_who, t1 = self._ahead_pairs(w, decoded & ~inside, slots) if ahead.any() else none
        if not len(rr) + len(a_rr):
            return count
        at = tuple(torch.from_numpy(np.r_[a, b]).to(self.device) for a, b in ((a_rr, rr), (a_cc, cc)))
        kinds = self.kind[np.r_[a_rr, rr], np.r_[a_who, who]]
        both = self.model.class_logits_by_kind(hidden[at], kinds).cpu()
        if len(a_rr):
            self._draw_ahead(both[: len(a_rr)], a_rr, a_who, t1)
        if not todo.any():
            return count
        logits = both[len(a_rr) :]
        tt = self.now[rr]
        u = counter_uniform(self.seed[rr], tt, who)
        temperature, top_p = self.config.temperature, self.config.top_p
        if self._draft is None:
            if self.guard is None:
                tok = sample_with_uniform(logits, temperature, top_p, u)
            else:
                tok = self.guard.sample(self, logits, rr, who, tt, u, temperature, top_p)
            self._finish(rr, who, tt, tok)
            return count
        # parallel: keep the exact pairs; the others are drafted anew from the tokens drawn for them
        drafts = self._draft[rr, who]
        tables = None  # the guard's probabilities and CDF of every pair, made once for both draws
        if self.guard is not None and temperature > 0 and top_p == 1.0:
            tables = draw_tables(logits, temperature)
            tok = sample_from_cdf(tables[1], u)
        else:
            tok = sample_with_uniform(logits, temperature, top_p, u)
        if self.guard is not None:
            # every pair is guarded: the drafts are guarded draws (parallel.guard_drafts), and the pairs
            # after a row's first miss are drafted anew from guarded draws (unguarded ones miss where the
            # guard acts)
            view = guard_view(self, rr, who, drafts)
            tok = self.guard.sample(self, logits, rr, who, tt, u, temperature, top_p, view, tables)
        last = accepted(rr, cc, tok, drafts, self.B)
        self._draft[rr, who] = tok
        keep = cc <= last[rr]
        self._finish(rr[keep], who[keep], tt[keep], tok[keep])
        self._keep_logits(rr[keep], who[keep], tt[keep], logits[torch.from_numpy(np.flatnonzero(keep))])
        whole = kept_every_draft(rr, rr, tok, drafts, self.B) | (last < 0)
        return np.where(whole, count, last + 1)

    def _guard_drafts(self, stepping: np.ndarray, from_ahead: np.ndarray, coupled: np.ndarray) -> None:
        """:func:`~trajeglish_env.sampler.parallel.guard_drafts` of the drafts drawn from logits: the
        look-ahead's (``from_ahead [B,N]``), else the step before's (``coupled [B,N]``)."""
        if self._drawn_logits.shape[:2] != (self.B, self.N):
            return
        logits = np.where(from_ahead[..., None], self._ahead_logits, self._drawn_logits)
        config = self.config
        assert self.guard is not None
        has = from_ahead | coupled
        guard_drafts(self, self.guard, stepping, logits, has, config.temperature, config.top_p)

    def _ahead_pairs(
        self, w: Window, where: np.ndarray, slots: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pairs ``(rows, offsets, agents, next steps)`` of the look-ahead positions ``where [B,n]`` whose
        next-step drafts are drawn: the controlled agents acting in the next step (a later call of the same
        context redraws them from better inputs; a later context keeps those of an earlier one)."""
        rr, cc = np.nonzero(where & (np.take_along_axis(w.slots, slots, 1) >= 0))
        who = w.slots[rr, slots[rr, cc]]
        t1 = self.now[rr] + 1
        pick = self.row_controlled[rr, who] & (self._ahead_rank[rr, who] >= self._rank[rr])
        pick &= t1 < self.end[rr]
        pick &= ~self.known[rr, who, np.minimum(t1, self.T - 2)]
        return rr[pick], cc[pick], who[pick], t1[pick]

    def _draw_ahead(self, logits: torch.Tensor, rr: np.ndarray, who: np.ndarray, t1: np.ndarray) -> None:
        """Draw next-step drafts (unguarded, each with its own number of the next step) of the look-ahead's
        pairs (:meth:`_ahead_pairs`) from their class ``logits [n,V]``."""
        u = counter_uniform(self.seed[rr], t1, who)
        config = self.config
        drawn = logits.float().numpy()
        self._logit_buffers(drawn.shape[1])
        self._ahead_logits[rr, who] = drawn  # kept for the guard (parallel.guard_drafts)
        self._ahead[rr, who] = draft_draws(drawn, config.temperature, config.top_p, u)
        self._ahead_rank[rr, who] = self._rank[rr]

    def _read_span(self, wanted: np.ndarray, n: int) -> tuple[int, int]:
        """The input slots ``(first, stop)`` of a call whose outputs are read (``wanted [B,n]``): the known
        agents that open a subset (those that acted in an earlier one) and padding are only context, so
        the last layer computes their keys and values only. At least one slot."""
        used = np.flatnonzero(wanted.any(axis=0))
        first, stop = (int(used[0]), int(used[-1]) + 1) if len(used) else (0, 0)
        stop = min(n, max(stop, first + 1))
        return max(0, min(first, stop - 1)), stop

    def _keep_logits(self, rr: np.ndarray, who: np.ndarray, tt: np.ndarray, logits: torch.Tensor) -> None:
        """Keep the class logits ``[n,V]`` that agents ``who`` of rows ``rr`` drew their tokens of steps
        ``tt`` from: the next step drafts from them (:func:`~.parallel.coupled_drafts`)."""
        self._logit_buffers(logits.shape[1])
        self._drawn_logits[rr, who] = logits.numpy()
        self._drawn_at[rr, who] = tt

    def _logit_buffers(self, classes: int) -> None:
        """Size the kept class logits (``[B,N,classes]``: those drawn from, those the look-ahead drew
        from) to the rows' agents (cleared when they grow)."""
        if self._drawn_logits.shape != (self.B, self.N, classes):
            self._drawn_logits = np.zeros((self.B, self.N, classes), np.float32)
            self._ahead_logits = np.zeros_like(self._drawn_logits)
            self._drawn_at = np.full((self.B, self.N), -1, np.int64)

    def _coupled_drafts(self, wanted: np.ndarray) -> np.ndarray:
        """:func:`~trajeglish_env.sampler.parallel.coupled_drafts` of the kept logits, where ``wanted``."""
        if self._drawn_at.shape != (self.B, self.N):
            return np.full((self.B, self.N), -1, np.int64)
        config = self.config
        logits, at = self._drawn_logits, self._drawn_at
        return coupled_drafts(self, logits, at, config.temperature, config.top_p, wanted)

    def _finish(self, rr: np.ndarray, who: np.ndarray, tt: np.ndarray, tok: np.ndarray) -> None:
        """Record the drawn tokens ``tok`` of agents ``who`` of rows ``rr`` at steps ``tt`` and states."""
        self.tokens[rr, who, tt] = tok
        self.known[rr, who, tt] = True
        nxt = to_global(self.mxyh[rr, who, tt], self.vocab.templates[self.kind[rr, who], tok])
        self.mxyh[rr, who, tt + 1] = nxt
        self.xyh[rr, who, tt + 1] = nxt
        self.valid[rr, who, tt + 1] = True

    def _pending_external(self, stepping: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """External agents alive at this step whose next state has not been supplied (acting order)."""
        r_ix = np.arange(self.B)[:, None]
        need = (
            self.row_external & ~self.known[r_ix, :, t[:, None]][:, 0] & self.valid[r_ix, :, t[:, None]][:, 0]
        )
        need &= stepping[:, None]
        if not need.any():
            return None
        rr, aa = np.nonzero(need)
        order = np.lexsort((aa, self.row_priority[rr, aa], rr))
        return rr[order], aa[order]

    def step(self) -> None:
        """Advance every stepping row by one step (no external agent may be waiting)."""
        pending = self._advance()
        if pending is not None:
            raise RuntimeError(
                f"external agents {pending[1].tolist()} of rows {pending[0].tolist()} must be supplied "
                "before the step can finish"
            )

    def run(self) -> None:
        """Step until every row reaches its horizon (no external agents)."""
        while self.stepping.any():
            self.step()


class RolloutEngine(BatchEngine):
    """``R`` rollouts of one scene (rows ``0..R-1``; rollout ``r`` draws from sub-stream
    ``first_rollout + r`` of the seed, so rollouts split over engines are those of one engine). Keeps the
    single-scene view: ``t``, ``T`` and ``N`` are ints, ``controlled``/``external``/
    ``replay`` are ``[N]``, :meth:`advance` returns one external agent and :meth:`supply` takes its
    states in every rollout."""

    def __init__(
        self,
        ckpt: Checkpoint,
        scenario: Scenario,
        rollouts: int,
        horizon: int,
        controlled: np.ndarray,
        external: np.ndarray | None = None,
        current_index: int | None = None,
        priority: np.ndarray | None = None,
        config: SamplingConfig | None = None,
        cache_dtype: torch.dtype | None = None,
        first_rollout: int = 0,
    ):
        config = config or SamplingConfig()
        super().__init__(ckpt, rollouts, config, cache_dtype)
        self.sc = scenario
        spec = RowSpec(scenario, horizon, controlled, external, current_index, priority)
        streams = stream_seed(config.seed, first_rollout + np.arange(self.R))
        self.start_rows(np.arange(self.R), spec, streams)
        self.controlled = self.row_controlled[0].copy()
        self.external = self.row_external[0].copy()
        self.replay = ~(self.controlled | self.external)
        self.priority = self.row_priority[0].copy()
        self.current = int(self.now[0])

    @property
    def R(self) -> int:
        """Number of rollouts."""
        return self.B

    @property
    def t(self) -> int:
        """The step being played (the same in every rollout)."""
        return int(self.now[0])

    def advance(self) -> int | None:  # type: ignore[override]
        """The next external agent to supply (for every rollout), or None when the step is complete."""
        pending = self._advance()
        return None if pending is None else int(pending[1][0])

    def supply(  # type: ignore[override]
        self, agent: int, next_xyh: np.ndarray, valid: bool | np.ndarray = True
    ) -> None:
        """Set the state at ``t + 1`` of external ``agent`` in every rollout (``next_xyh [R,3]``)."""
        if not self.external[agent]:
            raise ValueError(f"agent {agent} (track {self.sc.track_id[agent]}) is not external")
        rows = np.arange(self.R)
        super().supply(rows, np.full(self.R, agent), next_xyh, np.broadcast_to(valid, (self.R,)))
