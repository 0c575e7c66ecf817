"""Model contexts ("windows") of :class:`~trajeglish_env.sampler.engine.BatchEngine`: at recompute steps
the active agents of a row are split into subsets (:mod:`~trajeglish_env.sampler.subsets`); each subset
rank ``k`` of every row is one :class:`Window` whose cache is encoded from the subset's scene and primed
with the known tokens of its first steps (see the engine's module docstring).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.geometry import to_local
from trajeglish_env.model.layers import DecoderCache
from trajeglish_env.model.map_chunks import MapChunks, chunk_map, map_anchors, nearest_chunks, signal_classes
from trajeglish_env.model.masks import START, input_shift
from trajeglish_env.model.neighbours import OWN_FEATURES, PAIR_FEATURES, NeighbourView, neighbour_view
from trajeglish_env.model.network import SceneInputs, TrajeglishModel
from trajeglish_env.sampler.row_roads import RowRoads
from trajeglish_env.sampler.rows import RowSpec, RowStates
from trajeglish_env.sampler.subsets import SubsetPlan, admit, plan_subsets
from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

MAP_RADIUS = 100.0  # metres around a window's centre agent, as in training windows
# rows encoded and primed per model call when windows are (re)built (activations stay in cache): 16 rather
# than 8 runs the WOMD scene's 16 x 40 rollouts 2-3 % faster (12.9 / 12.7 against 13.3 / 13.0 s) and a
# batch of 128 scenes alike (26.2 / 26.3 against 26.6 / 26.4 s), the same tokens (stop 60)
ROW_BLOCK = 16


@dataclass
class Window:
    """Subset rank ``k`` of every row: agent slots, window start step, cache and agent embeddings."""

    slots: np.ndarray  # [B, A] agent indices (-1 padding)
    start: np.ndarray  # [B] s0: the step of the initial states
    cache: DecoderCache
    agents: torch.Tensor  # [B, A, C]
    kind: torch.Tensor  # [B, A]


class WindowedRows(RowStates):
    """:class:`RowStates` with the model contexts of every row: ``plan`` (a row's subsets),
    ``window_step`` (when they were built), ``windows`` (one per subset rank). Windows start ``prime``
    steps before the step they are built at and are rebuilt every ``every`` steps; ``subsets`` is the
    splitting rule and ``cache_dtype`` the dtype of the self-attention caches."""

    def __init__(
        self,
        model: TrajeglishModel,
        vocab: MotionVocabulary,
        rows: int,
        prime: int,
        every: int,
        subsets: str,
        cache_dtype: torch.dtype,
    ):
        super().__init__(rows, vocab)
        self.model = model
        self.device = model.start.device  # the engine's state stays on the host; the model's here
        self.cfg = model.cfg
        self.prime, self.every, self.subsets = prime, every, subsets
        self.cache_dtype = cache_dtype
        self.chunks: list[MapChunks | None] = [None] * self.B
        self.plan: list[SubsetPlan | None] = [None] * self.B
        self.num_subsets = np.zeros(self.B, dtype=np.int64)
        self.window_step = np.full(self.B, -1, dtype=np.int64)
        self.windows: list[Window] = []
        self._chunk_cache: dict[int, tuple[Scenario, MapChunks]] = {}
        self.roads: RowRoads | None = None  # the road around each agent (models with lane_input)
        if model.lanes is not None:
            self.roads = RowRoads(self.B, model.lanes, self.cfg.d_model, self.device, prime + 1)

    def start_rows(self, rows: np.ndarray | list[int], spec: RowSpec, seeds: np.ndarray | list[int]) -> None:
        """See :meth:`RowStates.start_rows`; the rows' windows are built at their next step."""
        super().start_rows(rows, spec, seeds)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        chunks = self._map_chunks(spec.scenario)
        for r in rows:
            self.chunks[r], self.plan[r] = chunks, None
        self.window_step[rows] = -1
        self.num_subsets[rows] = 0
        if self.roads is not None:
            self.roads.reset(rows)

    def _map_chunks(self, sc: Scenario) -> MapChunks:
        hit = self._chunk_cache.get(id(sc))
        if hit is None or hit[0] is not sc:
            if len(self._chunk_cache) > 4 * self.B + 64:
                self._chunk_cache.clear()
            hit = (sc, chunk_map(sc, self.cfg.points_per_polyline, self.cfg.map_stride))
            self._chunk_cache[id(sc)] = hit
        return hit[1]

    def _needs_windows(self) -> np.ndarray:
        since = self.now - self.window_step
        return self.stepping & ((self.window_step < 0) | ((since % self.every == 0) & (since != 0)))

    def _build_windows(self, rows: np.ndarray) -> None:
        """Plan subsets of ``rows`` at their step and encode + prime each subset rank for them; rows whose
        histories are identical (the rollouts of one scene at their first step) are built once and
        copied."""
        first, copies = self._identical_rows(rows)
        self._build_distinct(first)
        if len(copies):
            self._copy_windows(first[copies[:, 1]], copies[:, 0])

    def _identical_rows(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``rows`` reduced to one per group of identical ones (same scene, step and everything its windows
        are built from), and ``[k,2]`` (row, index of its group's row) of the others."""
        cheap = [(id(self.scenes[b]), id(self.chunks[b]), int(self.now[b]), int(self.first[b])) for b in rows]
        # rows of one scene share a history only where none has drawn yet: at the scene's current step
        shared = {
            k
            for k, n in Counter(cheap).items()
            if n > 1 and k[2] == self.scenes[rows[cheap.index(k)]].current_index  # type: ignore[union-attr]
        }
        seen: dict[tuple[object, ...], int] = {}
        kept: list[int] = []
        copies: list[tuple[int, int]] = []
        for b, base in zip(rows.tolist(), cheap, strict=True):
            key: tuple[object, ...] = (b,)  # a row alone of its scene and step is kept as it is
            if base in shared:
                t = base[2]
                history = (self.mxyh[b, :, : t + 1], self.valid[b, :, : t + 1], self.tokens[b, :, :t])
                arrays = (*history, self.known[b, :, :t], self.row_priority[b], self.row_controlled[b])
                arrays += (self.row_external[b], self.size[b], self.kind[b])
                key = (*base, b"".join(a.tobytes() for a in arrays))
            hit = seen.get(key)
            if hit is None:
                seen[key] = len(kept)
                kept.append(b)
            else:
                copies.append((b, hit))
        return np.array(kept, np.int64), np.array(copies, np.int64).reshape(-1, 2)

    def _copy_windows(self, source: np.ndarray, target: np.ndarray) -> None:
        """Give rows ``target`` the plans and windows (caches included) of rows ``source``."""
        src, dst = torch.from_numpy(source).to(self.device), torch.from_numpy(target).to(self.device)
        for b, a in zip(target.tolist(), source.tolist(), strict=True):
            self.plan[b] = self.plan[a]
        self.acting_rank[target] = self.acting_rank[source]
        self.num_subsets[target] = self.num_subsets[source]
        self.window_step[target] = self.window_step[source]
        if self.roads is not None:
            self.roads.reset(target)
        for w in self.windows:
            w.slots[target], w.start[target] = w.slots[source], w.start[source]
            w.agents[dst], w.kind[dst] = w.agents[src], w.kind[src]
            c = w.cache
            for part in (c.self_k, c.self_v, c.cross_k, c.cross_v):
                for tensor in part:
                    tensor[dst] = tensor[src]
            c.memory_mask[dst] = c.memory_mask[src]
        self._note_full()

    def _build_distinct(self, rows: np.ndarray) -> None:
        """:meth:`_build_windows` for rows built one by one."""
        A = self.cfg.max_agents
        t = self.now[rows]
        s0 = np.maximum(0, t - self.prime)
        plans = [
            plan_subsets(
                self.mxyh[b, :, self.now[b], :2],
                self.valid[b, :, self.now[b]],
                A,
                self.first[b],
                self.row_priority[b],
                self.subsets,
            )
            for b in rows
        ]
        counts = np.array([p.num_subsets for p in plans], dtype=np.int64)
        while len(self.windows) < counts.max(initial=0):
            cache = self.model.empty_cache(self.B, self.cache_dtype)
            self.windows.append(
                Window(
                    np.full((self.B, A), -1, dtype=np.int64),
                    np.zeros(self.B, dtype=np.int64),
                    cache,
                    torch.zeros(self.B, A, self.cfg.d_model, device=self.device),
                    torch.zeros(self.B, A, dtype=torch.long, device=self.device),
                )
            )
        for i, b in enumerate(rows):
            self._set_plan(b, plans[i])
        self.num_subsets[rows] = counts
        self.window_step[rows] = t
        for k, w in enumerate(self.windows):
            w.start[rows] = s0
            has = counts > k
            w.slots[rows[~has]] = -1
            if has.any():
                self._encode_rank(k, rows[has], [plans[i] for i in np.flatnonzero(has)])
        self._note_full()

    def _set_plan(self, row: int, plan: SubsetPlan) -> None:
        """Row ``row``'s subset plan and each agent's place in its acting order (``acting_rank``)."""
        self.plan[row] = plan
        self.acting_rank[row] = -1
        self.acting_rank[row, plan.acting_order] = np.arange(len(plan.acting_order))

    def _admit(self, rows: np.ndarray, agents: np.ndarray) -> np.ndarray:
        """Give each of ``agents`` (of ``rows``), just become active (the log brings them in), a slot in an
        existing window of its row (:func:`~trajeglish_env.sampler.subsets.admit`): it acts last there,
        and only the windows that changed are encoded and primed anew, from ``prime`` steps back; the
        others keep their contexts (and are rebuilt when they were due to be). Returns the rows where an
        agent found no room: their windows are to be planned anew."""
        changed: dict[int, list[int]] = {}
        failed: list[int] = []
        for b, a in zip(rows.tolist(), agents.tolist(), strict=True):
            plan, here = self.plan[b], self.mxyh[b, :, self.now[b], :2]
            got = None if plan is None else admit(plan, a, here, self.row_external[b])
            if got is None:
                failed.append(b)
                continue
            self._set_plan(b, got[0])
            k = got[1]
            changed.setdefault(k, []).append(b)
        for k, members in sorted(changed.items()):
            ranked = np.setdiff1d(members, failed)  # sorted, unique
            plans = [p for b in ranked.tolist() if (p := self.plan[b]) is not None]  # every one admitted
            if len(ranked):
                self._encode_rank(k, ranked, plans)
        self._note_full()
        return np.unique(np.asarray(failed, dtype=np.int64))

    @torch.no_grad()
    def _encode_rank(self, k: int, rows: np.ndarray, plans: list[SubsetPlan]) -> None:
        """Encode subset rank ``k`` of ``rows`` (sorted; their ``plans``) and prime it with the known tokens
        of the ``prime`` steps before their step."""
        w = self.windows[k]
        t = self.now[rows]
        s0 = np.maximum(0, t - self.prime)
        w.start[rows] = s0
        for n in np.unique(t - s0):  # rows primed with the same number of steps
            group = t - s0 == n
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

    def _note_full(self) -> None:
        """Every slot of every row real: the memory masks are all True (the model skips them)."""
        for w in self.windows:
            w.cache.memory_full = bool((w.slots >= 0).all())

    def _scene_inputs(
        self, rows: np.ndarray, slots: np.ndarray, s0: np.ndarray, centres: np.ndarray
    ) -> SceneInputs:
        """Encoder inputs of one subset per row: initial states at ``s0`` (or the first valid step after
        it, for agents that appeared later) in the frame of the centre agent, and the nearest map (with its
        signals at ``s0``)."""
        c = self.cfg
        real = slots >= 0
        idx = np.where(real, slots, 0)
        r_ix = rows[:, None]
        steps = np.arange(self.T)
        window = (steps[None] >= s0[:, None]) & (steps[None] <= self.now[rows][:, None])  # [r, T]
        seg = self.valid[r_ix, idx] & window[:, None]  # [r, A, T]
        first = np.where(seg.any(-1), np.argmax(seg, axis=-1), s0[:, None])
        init = self.mxyh[r_ix, idx, first]
        prior = np.maximum(first - 1, 0)  # the step before: the agents' speed and turn rate ("ahead" map)
        before, before_ok = self.mxyh[r_ix, idx, prior], self.valid[r_ix, idx, prior] & (first > 0)
        cseg = self.valid[rows, centres] & (steps[None] >= s0[:, None])
        cfirst = np.where(cseg.any(-1), np.argmax(cseg, axis=-1), s0)
        frames = self.mxyh[rows, centres, cfirst]
        local = to_local(frames[:, None, :], init)
        m = len(rows)
        pts = np.zeros((m, c.max_polylines, c.points_per_polyline, 2), dtype=np.float32)
        pmask = np.zeros(pts.shape[:3], dtype=bool)
        mkind = np.zeros((m, c.max_polylines), dtype=np.int64)
        mmask = np.zeros((m, c.max_polylines), dtype=bool)
        msignal = np.zeros((m, c.max_polylines), dtype=np.int64)
        for i, b in enumerate(rows):
            chunks, sc = self.chunks[b], self.scenes[b]
            # the signals at the window's first step, as in training (read only by models with signal_input)
            signal = signal_classes(sc, chunks, int(s0[i])) if c.signal_input and sc is not None else None
            anchors = map_anchors(c.map_select, init[i, real[i]], before[i, real[i]], before_ok[i, real[i]])
            pts[i], pmask[i], mkind[i], mmask[i], msignal[i] = nearest_chunks(
                chunks, frames[i], c.max_polylines, MAP_RADIUS, signal, anchors
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
            map_signal=torch.from_numpy(msignal).to(dev),
        )

    def _joint(self, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """Joint ids of the tokens of ``agents [r,n]`` (-1 padding) at ``steps [r,n]`` (-1: unknown; the
        draft of an undecided token of the step being decoded in parallel)."""
        safe = np.maximum(agents, 0)
        r_ix = rows[:, None]
        tok = self.tokens[r_ix, safe, steps]
        known = self.known[r_ix, safe, steps]
        ok = (agents >= 0) & known & (tok >= 0)
        if self._draft is not None:
            draft = self._draft[r_ix, safe]
            use = (agents >= 0) & ~known & (steps == self.now[r_ix]) & (draft >= 0)
            tok, ok = np.where(use, draft, tok), ok | use
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

    def _view(
        self,
        rows: np.ndarray,
        slots: np.ndarray,
        s0: np.ndarray,
        positions: np.ndarray,
        needed: np.ndarray | None = None,
    ) -> NeighbourView | None:
        """Features ``[r,n]`` of window ``positions [r,n]`` (models that read states; else None): each
        position's agent reads the model's states of its window's agents at its step, and (``lane_input``)
        the road around it there (only at the positions ``needed [r,n]`` when given: the others' outputs are
        not used)."""
        if not self.cfg.reads_states:
            return None
        A = self.cfg.max_agents
        tau = positions // A
        steps = np.minimum(s0[:, None] + tau, self.T - 1)[:, :, None]  # [r,n,1]
        real = slots >= 0
        r_ix, a_ix = rows[:, None, None], np.where(real, slots, 0)[:, None, :]  # [r,1,1], [r,1,A]

        def at(step: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
            ok = self.valid[r_ix, a_ix, step] & real[:, None, :]  # [r,n,A]
            return torch.from_numpy(self.mxyh[r_ix, a_ix, step]), torch.from_numpy(ok)

        r, n = positions.shape
        if self.cfg.neighbour_input:
            (cur, ok), (prev, prev_ok) = at(steps), at(np.maximum(steps - 1, 0))
            prev_ok &= torch.from_numpy(tau > 0)[..., None]  # a window's first step reads no velocity
            size = torch.from_numpy(self.size[r_ix, a_ix]).expand(-1, n, -1, -1)
            focal = torch.from_numpy(positions % A)[..., None]  # [r,n,1]
            view = neighbour_view(cur, ok, prev, prev_ok, size, focal)
            view = NeighbourView(view.own[:, :, 0], view.pairs[:, :, 0], view.mask[:, :, 0])
        else:  # the road alone: no neighbour features (none read)
            own, pairs = torch.zeros(r, n, OWN_FEATURES), torch.zeros(r, n, 0, PAIR_FEATURES)
            view = NeighbourView(own, pairs, torch.zeros(r, n, 0, dtype=torch.bool))
        if self.cfg.lane_input:
            agents = np.where(real, slots, -1)[np.arange(len(rows))[:, None], positions % A]  # [r,n]
            if needed is not None:
                agents = np.where(needed, agents, -1)
            assert self.roads is not None
            code = self.roads.codes(self, rows, agents, steps[:, :, 0])
            view = NeighbourView(view.own, view.pairs, view.mask, road_code=code)
        return view.to(self.device)

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
        self.model.prime(cache, agents, carried, own, self._view(rows, slots, s0, positions))


def _row_blocks(rows: np.ndarray, size: int) -> list[slice]:
    """Slices of ``rows`` (sorted) into blocks of at most ``size`` consecutive row numbers."""
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    blocks = []
    for run in np.split(np.arange(len(rows)), breaks):
        blocks += [
            slice(int(run[i]), int(run[min(i + size, len(run)) - 1]) + 1) for i in range(0, len(run), size)
        ]
    return blocks
