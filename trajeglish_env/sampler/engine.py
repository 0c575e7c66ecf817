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
the batch: draws are counter-based (:func:`~trajeglish_env.sampling.counter_uniform` of the row seed,
the step and the agent) and inference is batch-invariant (:mod:`trajeglish_env.model.layers`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.geometry import to_global, to_local
from trajeglish_env.map_chunks import MapChunks, chunk_map, nearest_chunks
from trajeglish_env.model.config import Variant
from trajeglish_env.model.layers import DecoderCache
from trajeglish_env.model.masks import input_shift
from trajeglish_env.model.network import SceneInputs
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.subsets import SubsetPlan, plan_subsets
from trajeglish_env.sampling import START, counter_uniform, sample_with_uniform, stream_seed
from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.tokenize import tokenize

MAP_RADIUS = 100.0  # metres around a window's centre agent, as in training windows
ROW_BLOCK = 8  # rows encoded and primed per model call when windows are (re)built: activations stay in cache


@dataclass(frozen=True)
class RowSpec:
    """What one row simulates: ``controlled [N]`` agents the model drives, ``external [N]`` agents whose
    states are supplied from outside (others replay the log), ``horizon`` steps after ``current_index``
    (default: the scene's), acting ``priority [N]`` (lower first), and ``first``: the agent whose model
    context goes first (default: the sdc)."""

    scenario: Scenario
    horizon: int
    controlled: np.ndarray
    external: np.ndarray | None = None
    current_index: int | None = None
    priority: np.ndarray | None = None
    first: int | None = None


@dataclass
class _Window:
    """Subset rank ``k`` of every row: agent slots, window start step, cache and agent embeddings."""

    slots: np.ndarray  # [B, A] agent indices (-1 padding)
    start: np.ndarray  # [B] s0: the step of the initial states
    cache: DecoderCache
    agents: torch.Tensor  # [B, A, C]
    kind: torch.Tensor  # [B, A]


class BatchEngine:
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
        config = config or SamplingConfig()
        self.model = ckpt.model.eval()
        self.device = self.model.start.device  # the engine's state stays on the host; the model's here
        self.vocab = ckpt.vocabulary
        self.cfg = self.model.cfg
        self.config = config
        self.cache_dtype = cache_dtype = config.torch_cache_dtype if cache_dtype is None else cache_dtype
        # the float32 single-query attention kernel rounds differently from the multi-query one: pad to 2
        # queries so that a row's result never depends on the chunk lengths of the other rows
        self._min_queries = 1 if cache_dtype == torch.bfloat16 else 2
        self.every = config.every(self.cfg.steps)
        self.prime = config.prime(self.cfg.steps)
        self.B = int(rows)
        self.N, self.T = 0, 2
        self._allocate(1, 2)
        self.live = np.zeros(self.B, dtype=bool)
        self.now = np.zeros(self.B, dtype=np.int64)
        self.end = np.zeros(self.B, dtype=np.int64)
        self.seed = np.zeros(self.B, dtype=np.uint64)
        self.first = np.zeros(self.B, dtype=np.int64)
        self.handover_step = np.full(self.B, -1, dtype=np.int64)
        self.scenes: list[Scenario | None] = [None] * self.B
        self.chunks: list[MapChunks | None] = [None] * self.B
        self.plan: list[SubsetPlan | None] = [None] * self.B
        self.num_subsets = np.zeros(self.B, dtype=np.int64)
        self.window_step = np.full(self.B, -1, dtype=np.int64)
        self.windows: list[_Window] = []
        self._in_step = False  # a step has begun (windows planned) and is not finished
        self._rank = 0  # subset rank being decoded in this step
        self._slot = np.zeros(self.B, dtype=np.int64)  # per row: next slot of that rank to decode
        self._supplied: list[tuple[np.ndarray, ...]] = []  # supplies whose tokens are not computed yet
        self._chunk_cache: dict[int, tuple[Scenario, MapChunks]] = {}

    # ------------------------------------------------------------------ storage
    def _allocate(self, n: int, t: int) -> None:
        """Grow the per-row arrays to ``n`` agents and ``t`` steps (padding: absent, decided)."""
        n, t = max(n, self.N), max(t, self.T)
        if n == self.N and t == self.T and hasattr(self, "xyh"):
            return
        B = self.B

        def grow(old: np.ndarray | None, shape: tuple[int, ...], fill: object, dtype: object) -> np.ndarray:
            new = np.full(shape, fill, dtype=dtype)
            if old is not None:
                new[tuple(slice(0, s) for s in old.shape)] = old
            return new

        get = self.__dict__.get
        self.xyh = grow(get("xyh"), (B, n, t, 3), 0.0, np.float64)
        self.mxyh = grow(get("mxyh"), (B, n, t, 3), 0.0, np.float64)
        self.valid = grow(get("valid"), (B, n, t), False, bool)
        self.tokens = grow(get("tokens"), (B, n, t - 1), -1, np.int64)
        self.known = grow(get("known"), (B, n, t - 1), True, bool)
        self.row_controlled = grow(get("row_controlled"), (B, n), False, bool)
        self.row_external = grow(get("row_external"), (B, n), False, bool)
        self.row_priority = grow(get("row_priority"), (B, n), 0.0, np.float64)
        self.handover = grow(get("handover"), (B, n), False, bool)
        self.size = grow(get("size"), (B, n, 2), 1.0, np.float64)
        self.kind = grow(get("kind"), (B, n), 0, np.int64)
        self.N, self.T = n, t

    def _map_chunks(self, sc: Scenario) -> MapChunks:
        hit = self._chunk_cache.get(id(sc))
        if hit is None or hit[0] is not sc:
            if len(self._chunk_cache) > 4 * self.B + 64:
                self._chunk_cache.clear()
            hit = (sc, chunk_map(sc, self.cfg.points_per_polyline))
            self._chunk_cache[id(sc)] = hit
        return hit[1]

    # ------------------------------------------------------------------ rows
    def start_rows(self, rows: np.ndarray | list[int], spec: RowSpec, seeds: np.ndarray | list[int]) -> None:
        """(Re)start ``rows`` on ``spec``, row ``rows[i]`` drawing from ``seeds[i]`` (an unfinished step of
        the other rows is undone, see :meth:`cancel_step`)."""
        self.cancel_step()
        self._tokenize_supplied()
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        seeds = np.asarray(seeds, dtype=np.uint64).reshape(-1)
        if len(rows) != len(seeds) or ((rows < 0) | (rows >= self.B)).any():
            raise ValueError(
                f"start_rows: {len(rows)} rows in 0..{self.B - 1} need as many seeds, got {seeds}"
            )
        sc = spec.scenario
        n = sc.num_agents
        cur = sc.current_index if spec.current_index is None else int(spec.current_index)
        if not 0 <= cur < sc.num_steps:
            raise ValueError(f"current_index {cur} out of range for {sc.num_steps} steps")
        if int(spec.horizon) < 1:
            raise ValueError(f"horizon must be >= 1, got {spec.horizon}")
        controlled = _agent_mask(spec.controlled, n, "controlled")
        external = (
            _agent_mask(spec.external, n, "external") if spec.external is not None else np.zeros(n, bool)
        )
        if (controlled & external).any():
            raise ValueError(
                f"agents {np.flatnonzero(controlled & external).tolist()} are both controlled and external"
            )
        missing = np.flatnonzero(controlled & ~sc.valid[:, cur])
        if len(missing):
            raise ValueError(
                f"controlled agents must be valid at the current step {cur}; track ids "
                f"{sc.track_id[missing].tolist()} are not"
            )
        priority = np.zeros(n) if spec.priority is None else np.asarray(spec.priority, dtype=np.float64)
        if priority.shape != (n,):
            raise ValueError(f"priority: expected shape ({n},), got {priority.shape}")
        T = cur + 1 + int(spec.horizon)
        self._allocate(n, T)
        # what is fixed before the rollout: everyone's history, replay agents' whole future
        logged = np.zeros((n, T, 3))
        lvalid = np.zeros((n, T), dtype=bool)
        keep = min(T, sc.num_steps)
        logged[:, :keep] = sc.xyh[:, :keep]
        lvalid[:, :keep] = sc.valid[:, :keep]
        replay = ~(controlled | external)
        fixed = lvalid & ((np.arange(T) <= cur)[None] | replay[:, None])
        tok = tokenize(self.vocab, logged, fixed, sc.size, sc.kind.astype(np.int64))
        for arr, fill in ((self.xyh, 0.0), (self.mxyh, 0.0), (self.valid, False), (self.tokens, -1)):
            arr[rows] = fill
        self.known[rows] = True
        self.xyh[rows, :n, :T] = np.where(fixed[..., None], logged, 0.0)
        self.mxyh[rows, :n, :T] = np.nan_to_num(tok.xyh)
        self.tokens[rows, :n, : T - 1] = tok.tokens
        unknown = controlled | external  # their future tokens are decided during the rollout
        self.known[np.ix_(rows, np.flatnonzero(unknown), np.arange(cur, T - 1))] = False
        valid = fixed.copy()
        valid[controlled, cur:] = True  # controlled agents exist for the whole rollout
        self.valid[rows, :n, :T] = valid
        self.row_controlled[rows] = False
        self.row_controlled[rows, :n] = controlled
        self.row_external[rows] = False
        self.row_external[rows, :n] = external
        self.row_priority[rows] = 0.0
        self.row_priority[rows, :n] = priority
        # a rollout past the log: the log's agents present at its last step go on as controlled agents
        self.handover[rows] = False
        if T > sc.num_steps:
            self.handover[rows, :n] = replay & sc.valid[:, -1]
        self.handover_step[rows] = sc.num_steps - 1 if T > sc.num_steps else -1
        self.size[rows] = 1.0
        self.size[rows, :n] = sc.size
        self.kind[rows] = 0
        self.kind[rows, :n] = sc.kind
        chunks = self._map_chunks(sc)
        for r in rows:
            self.scenes[r], self.chunks[r], self.plan[r] = sc, chunks, None
        self.now[rows], self.end[rows] = cur, T - 1
        self.seed[rows] = seeds
        self.first[rows] = sc.sdc if spec.first is None else int(spec.first)
        self.live[rows] = True
        self.window_step[rows] = -1
        self.num_subsets[rows] = 0

    def cancel_step(self) -> None:
        """Undo the unfinished step of every stepping row: the tokens decoded or supplied in it are forgotten
        (decoding it again draws the same ones, and overwrites the same cache positions), so rows can be
        (re)started or stopped as between steps."""
        self._supplied = []
        if not self._in_step:
            return
        rows = np.flatnonzero(self.stepping)
        r, a = np.nonzero(self.row_controlled[rows] | self.row_external[rows])
        rr, t = rows[r], self.now[rows[r]]
        self.known[rr, a, t] = False
        self.tokens[rr, a, t] = -1
        ext = self.row_external[rr, a]
        self.valid[rr[ext], a[ext], t[ext] + 1] = False
        self.xyh[rr[ext], a[ext], t[ext] + 1] = 0.0
        self._in_step = False

    def stop_rows(self, rows: np.ndarray | list[int]) -> None:
        """Take ``rows`` out of the simulation (they stop stepping until started again; an unfinished step
        of the others is undone, see :meth:`cancel_step`)."""
        self.cancel_step()
        self.live[np.asarray(rows, dtype=np.int64)] = False

    @property
    def stepping(self) -> np.ndarray:
        """``[B]`` rows that take part in the current step."""
        return self.live & (self.now < self.end)

    # ------------------------------------------------------------------ windows
    def _needs_windows(self) -> np.ndarray:
        since = self.now - self.window_step
        return self.stepping & ((self.window_step < 0) | ((since % self.every == 0) & (since != 0)))

    @torch.no_grad()
    def _build_windows(self, rows: np.ndarray) -> None:
        """Plan subsets of ``rows`` at their step and encode + prime each subset rank for them."""
        A, L = self.cfg.max_agents, self.cfg.max_agents * self.cfg.steps
        t = self.now[rows]
        s0 = np.maximum(0, t - self.prime)
        plans = [
            plan_subsets(
                self.mxyh[b, :, self.now[b], :2],
                self.valid[b, :, self.now[b]],
                A,
                self.first[b],
                self.row_priority[b],
                self.config.subsets,
            )
            for b in rows
        ]
        counts = np.array([p.num_subsets for p in plans], dtype=np.int64)
        while len(self.windows) < counts.max(initial=0):
            cache = self.model.empty_cache(self.B, L, A + self.cfg.latent_queries, self.cache_dtype)
            self.windows.append(
                _Window(
                    np.full((self.B, A), -1, dtype=np.int64),
                    np.zeros(self.B, dtype=np.int64),
                    cache,
                    torch.zeros(self.B, A, self.cfg.d_model, device=self.device),
                    torch.zeros(self.B, A, dtype=torch.long, device=self.device),
                )
            )
        for i, b in enumerate(rows):
            self.plan[b] = plans[i]
        self.num_subsets[rows] = counts
        self.window_step[rows] = t
        for k, w in enumerate(self.windows):
            w.start[rows] = s0
            has = counts > k
            w.slots[rows[~has]] = -1
            for n in np.unique(t[has] - s0[has]):  # rows primed with the same number of steps
                group = has & (t - s0 == n)
                sub = rows[group]
                slots = np.stack([plans[i].slots[k] for i in np.flatnonzero(group)])
                centres = np.array([plans[i].centres[k] for i in np.flatnonzero(group)])
                w.slots[sub] = slots
                scene = self._scene_inputs(sub, slots, s0[group], centres)
                for part in _row_blocks(sub, ROW_BLOCK):  # encoded and primed in place, block by block
                    rows_part = slice(int(sub[part.start]), int(sub[part.stop - 1]) + 1)
                    cache, part_scene = w.cache.rows(rows_part), scene.rows(part)
                    agents = self.model.encode_into(cache, part_scene)
                    if n:
                        self._prime(cache, agents, sub[part], slots[part], s0[group][part], int(n))
                    w.agents[rows_part] = agents
                    w.kind[rows_part] = part_scene.agent_kind
        for w in self.windows:  # every slot of every row real: the memory masks are all True
            w.cache.memory_full = bool((w.slots >= 0).all())

    def _scene_inputs(
        self, rows: np.ndarray, slots: np.ndarray, s0: np.ndarray, centres: np.ndarray
    ) -> SceneInputs:
        """Encoder inputs of one subset per row: initial states at ``s0`` (or the first valid step after
        it, for agents that appeared later) in the frame of the centre agent, and the nearest map."""
        c = self.cfg
        real = slots >= 0
        idx = np.where(real, slots, 0)
        r_ix = rows[:, None]
        steps = np.arange(self.T)
        window = (steps[None] >= s0[:, None]) & (steps[None] <= self.now[rows][:, None])  # [r, T]
        seg = self.valid[r_ix, idx] & window[:, None]  # [r, A, T]
        first = np.where(seg.any(-1), np.argmax(seg, axis=-1), s0[:, None])
        init = self.mxyh[r_ix, idx, first]
        cseg = self.valid[rows, centres] & (steps[None] >= s0[:, None])
        cfirst = np.where(cseg.any(-1), np.argmax(cseg, axis=-1), s0)
        frames = self.mxyh[rows, centres, cfirst]
        local = to_local(frames[:, None, :], init)
        m = len(rows)
        pts = np.zeros((m, c.max_polylines, c.points_per_polyline, 2), dtype=np.float32)
        pmask = np.zeros(pts.shape[:3], dtype=bool)
        mkind = np.zeros((m, c.max_polylines), dtype=np.int64)
        mmask = np.zeros((m, c.max_polylines), dtype=bool)
        for i, b in enumerate(rows):
            pts[i], pmask[i], mkind[i], mmask[i] = nearest_chunks(
                self.chunks[b], frames[i], c.max_polylines, MAP_RADIUS
            )
        dev = self.device
        return SceneInputs(
            agent_xyh=torch.from_numpy(np.where(real[..., None], local, 0.0)).float().to(dev),
            agent_size=torch.from_numpy(np.where(real[..., None], self.size[r_ix, idx], 1.0)).float().to(dev),
            agent_kind=torch.from_numpy(np.where(real, self.kind[r_ix, idx], 0)).to(dev),
            agent_mask=torch.from_numpy(real).to(dev),
            map_points=torch.from_numpy(pts).to(dev),
            map_point_mask=torch.from_numpy(pmask).to(dev),
            map_kind=torch.from_numpy(mkind).to(dev),
            map_mask=torch.from_numpy(mmask).to(dev),
        )

    def _joint(self, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """Joint ids of the tokens of ``agents [r,n]`` (-1 padding) at ``steps [r,n]`` (-1: unknown)."""
        safe = np.maximum(agents, 0)
        r_ix = rows[:, None]
        tok = self.tokens[r_ix, safe, steps]
        ok = (agents >= 0) & self.known[r_ix, safe, steps] & (tok >= 0)
        return np.where(ok, tok + self.kind[r_ix, safe] * self.cfg.vocab_size, -1)

    def _inputs(
        self, rows: np.ndarray, slots: np.ndarray, s0: np.ndarray, positions: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Carried and own-previous joint ids ``[r,n]`` of window ``positions [r,n]`` (see masks)."""
        A = self.cfg.max_agents
        q = positions - input_shift(self.cfg.variant, A)
        qs = np.maximum(q, 0)
        carried = self._joint(rows, np.take_along_axis(slots, qs % A, 1), s0[:, None] + qs // A)
        carried = np.where(q >= 0, carried, START)
        tau = positions // A
        own = self._joint(
            rows, np.take_along_axis(slots, positions % A, 1), s0[:, None] + np.maximum(tau - 1, 0)
        )
        own = np.where(tau > 0, own, -1)
        return torch.from_numpy(carried).to(self.device), torch.from_numpy(own).to(self.device)

    def _prime(
        self,
        cache: DecoderCache,
        agents: torch.Tensor,
        rows: np.ndarray,
        slots: np.ndarray,
        s0: np.ndarray,
        steps: int,
    ) -> None:
        """Feed a new window the known tokens of its first ``steps`` steps (teacher forcing, one chunk)."""
        A = self.cfg.max_agents
        positions = np.broadcast_to(np.arange(steps * A), (len(rows), steps * A))
        carried, own = self._inputs(rows, slots, s0, positions)
        self.model.prime(cache, agents, carried, own)

    # ------------------------------------------------------------------ stepping
    def advance(self) -> tuple[np.ndarray, np.ndarray] | None:
        """See :meth:`_advance`."""
        return self._advance()

    @torch.no_grad()
    def _advance(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Act the positions of the current step in order, for every stepping row. Returns
        ``(rows, agents)``: external agents whose next states are needed (supply them, then call again),
        or None when the step is complete (every stepping row is one step further). A waiting row holds
        while the others go on, so the call returns once no row can go further without a supply: every
        row then stands at its next external agent (inference is batch-invariant, so the grouping of rows
        into calls never changes a token).

        Each row runs through the slots of subset rank 0, 1, ... with its own cursor: a model call decodes,
        per row, the run of positions up to its next *blocker* (an agent to sample, or an external agent
        not supplied yet) in one chunk, since the inputs of all of them are known. Known agents (forced,
        padding, supplied externals) therefore cost no extra calls."""
        stepping = self.stepping
        if not stepping.any():
            raise RuntimeError("no row has steps left (start rows, or the horizon is reached)")
        self._tokenize_supplied()
        if not self._in_step:
            self._hand_over(np.flatnonzero(stepping & (self.now == self.handover_step)))
            rebuild = self._needs_windows()
            if rebuild.any():
                self._build_windows(np.flatnonzero(rebuild))
            self._in_step = True
            self._rank = 0
            self._slot = np.where(self.num_subsets > 0, 0, self.cfg.max_agents)
        A = self.cfg.max_agents
        ranks = int(self.num_subsets[stepping].max(initial=0))
        t_safe = np.minimum(self.now, self.T - 2)
        r_ix = np.arange(self.B)[:, None]
        while self._rank < ranks:
            w = self.windows[self._rank]
            safe = np.maximum(w.slots, 0)
            undecided = (w.slots >= 0) & ~self.known[r_ix, safe, t_safe[:, None]] & stepping[:, None]
            sample = undecided & self.row_controlled[r_ix, safe]
            wait = undecided & self.row_external[r_ix, safe] & self.valid[r_ix, safe, t_safe[:, None]]
            prev = np.clip(self._slot - 1, 0, A - 1)
            waiting = (self._slot > 0) & wait[np.arange(self.B), prev]
            active = stepping & (self._slot < A) & ~waiting
            if not active.any():
                if waiting.any():  # no row can go on without a supply: hand the waiting ones out
                    rows = np.flatnonzero(waiting)
                    return rows, w.slots[rows, prev[rows]]
                self._rank += 1
                self._slot = np.where(self.num_subsets > self._rank, 0, A)
                continue
            blocker = (sample | wait) if self.cfg.variant is Variant.TRAJEGLISH else np.zeros_like(sample)
            blocker &= np.arange(A)[None] >= self._slot[:, None]
            stop = np.where(blocker.any(1), np.argmax(blocker, axis=1), A - 1)
            count = np.where(active, stop - self._slot + 1, 0)
            self._decode_chunk(w, count, sample, stepping, t_safe)
            self._slot = self._slot + count
        late = self._pending_external(stepping, t_safe)
        if late is not None:
            return late
        rows = np.flatnonzero(stepping)
        self.known[rows, :, self.now[rows]] = True  # undecided tokens are unobserved from now on
        self.now[rows] += 1
        self._in_step = False
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
        self, w: _Window, count: np.ndarray, sample: np.ndarray, stepping: np.ndarray, t: np.ndarray
    ) -> None:
        """Decode ``count[b]`` positions of window ``w`` from each row's cursor; sample the agents to
        sample among them."""
        A = self.cfg.max_agents
        n = max(self._min_queries, int(count.max()))
        tau = self.now - w.start
        start = np.where(count > 0, tau * A + self._slot, 0)
        offsets = np.arange(n)
        inside = offsets[None] < count[:, None]
        positions = np.where(inside, start[:, None] + offsets, start[:, None])
        carried, own = self._inputs(np.arange(self.B), w.slots, w.start, positions)
        hidden = self.model.decode_at(w.cache, w.agents, carried, own, start, count)
        slots = positions % A
        todo = inside & np.take_along_axis(sample, slots, 1)
        if not todo.any():
            return
        rr, cc = np.nonzero(todo)
        who = w.slots[rr, slots[rr, cc]]
        rows_t = torch.from_numpy(rr).to(self.device)
        cols_t = torch.from_numpy(cc).to(self.device)
        logits = self.model.class_logits_by_kind(hidden[rows_t, cols_t], self.kind[rr, who]).cpu()
        tt = self.now[rr]
        u = counter_uniform(self.seed[rr], tt, who)
        tok = sample_with_uniform(logits, self.config.temperature, self.config.top_p, u)
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

    def supply(
        self,
        rows: np.ndarray,
        agents: np.ndarray,
        next_xyh: np.ndarray,
        valid: bool | np.ndarray = True,
    ) -> None:
        """Set the states at ``t + 1`` of external ``agents [n]`` of ``rows [n]`` (``next_xyh [n,3]``;
        ``valid=False``: the agent leaves the scene)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        agents = np.asarray(agents, dtype=np.int64).reshape(-1)
        n = len(rows)
        next_xyh = np.broadcast_to(np.asarray(next_xyh, dtype=np.float64), (n, 3))
        bad = ~self.row_external[rows, agents]
        if bad.any():
            b, a = int(rows[bad][0]), int(agents[bad][0])
            sc = self.scenes[b]
            track = sc.track_id[a] if sc is not None and a < sc.num_agents else "?"
            raise ValueError(f"agent {a} (track {track}) of row {b} is not external")
        if not self.stepping[rows].all():
            raise RuntimeError(f"rows {rows[~self.stepping[rows]].tolist()} are not stepping")
        t = self.now[rows]
        ok = np.broadcast_to(np.asarray(valid, dtype=bool), (n,)) & self.valid[rows, agents, t]
        self.xyh[rows, agents, t + 1] = np.where(ok[:, None], next_xyh, 0.0)
        self.valid[rows, agents, t + 1] = ok
        self.known[rows, agents, t] = True
        # the model's view (tokens) of all supplies is computed at once before the next model call
        self._supplied.append((rows, agents, t, next_xyh.copy(), ok))

    def _tokenize_supplied(self) -> None:
        """Tokenize every supplied state since the last call in one batch: the token from the model's view
        at ``t`` to the true state at ``t + 1``, and the model's view at ``t + 1`` (its tokenized state,
        re-anchored on the true state after a gap)."""
        if not self._supplied:
            return
        rows, agents, t, nxt, ok = (np.concatenate(parts) for parts in zip(*self._supplied, strict=True))
        self._supplied = []
        pair = np.stack([self.mxyh[rows, agents, t], nxt], 1)[:, None]  # [n,1,2,3]
        tok = tokenize(
            self.vocab,
            pair,
            np.stack([ok, ok], 1)[:, None],
            self.size[rows, agents][:, None, :],
            self.kind[rows, agents][:, None],
        )
        self.tokens[rows, agents, t] = np.where(ok, tok.tokens[:, 0, 0], -1)
        self.mxyh[rows, agents, t + 1] = np.where(ok[:, None], np.nan_to_num(tok.xyh[:, 0, 1]), 0.0)

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
    """``R`` rollouts of one scene (rows ``0..R-1``; rollout ``r`` draws from sub-stream ``r`` of the
    seed). Keeps the single-scene view: ``t``, ``T`` and ``N`` are ints, ``controlled``/``external``/
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
    ):
        config = config or SamplingConfig()
        super().__init__(ckpt, rollouts, config, cache_dtype)
        self.sc = scenario
        spec = RowSpec(scenario, horizon, controlled, external, current_index, priority)
        self.start_rows(np.arange(self.R), spec, stream_seed(config.seed, np.arange(self.R)))
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


def _row_blocks(rows: np.ndarray, size: int) -> list[slice]:
    """Slices of ``rows`` (sorted) into blocks of at most ``size`` consecutive row numbers."""
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    blocks = []
    for run in np.split(np.arange(len(rows)), breaks):
        blocks += [
            slice(int(run[i]), int(run[min(i + size, len(run)) - 1]) + 1) for i in range(0, len(run), size)
        ]
    return blocks


def _agent_mask(mask: np.ndarray, n: int, name: str) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.dtype != np.bool_ or mask.shape != (n,):
        raise ValueError(
            f"{name}: expected a bool mask of shape ({n},) (one entry per agent), "
            f"got {mask.dtype} {mask.shape}"
        )
    return mask
