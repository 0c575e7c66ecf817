"""Closed-loop token simulation of a scene, batched over rollouts, with a spatial and temporal sliding
window (paper appendix "Extended rollouts").

Roles per agent: *controlled* (the model samples its tokens), *replay* (follows given motion known in
advance, e.g. the log) and *external* (its next state is supplied step by step from outside, e.g. by an
RL policy in the environment). Replay and external agents keep their exact states; the model sees their
motion tokenized from its own (tokenized) view of them, so errors never accumulate.

Windows: at recompute steps the active agents are covered by subsets (:mod:`subsets`); each subset is a
model context whose initial states are the agents' states ``prime`` steps earlier (or their first valid
state after that), and whose caches are primed with the tokens of those steps. Within a timestep the
subsets act in order; an agent acts (is sampled) in the first subset holding it and is forced in later
ones. Everything is batched over rollouts: subset ``k`` of every rollout is one model batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.geometry import to_global, to_local
from trajeglish_env.map_chunks import MapChunks, chunk_map, nearest_chunks
from trajeglish_env.model.config import Variant
from trajeglish_env.model.masks import carried_position
from trajeglish_env.model.network import SceneInputs
from trajeglish_env.sampler.subsets import SubsetPlan, plan_subsets
from trajeglish_env.sampling import START, sample_logits
from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.tokenize import tokenize

MAP_RADIUS = 100.0  # metres around a window's centre agent, as in training windows


@dataclass(frozen=True)
class SamplingConfig:
    """Sampling settings: temperature/nucleus, the sliding window in time, and the seed."""

    temperature: float = 1.0
    top_p: float = 1.0
    prime_steps: int | None = (
        None  # steps of known motion re-fed when a window (re)starts; default steps // 4
    )
    recompute_every: int | None = None  # default: model steps - prime_steps
    seed: int = 0

    def prime(self, model_steps: int) -> int:
        prime = max(1, model_steps // 4) if self.prime_steps is None else self.prime_steps
        if not 0 <= prime < model_steps:
            raise ValueError(f"prime_steps={prime} must be in 0..{model_steps - 1} (the model's context)")
        return prime

    def every(self, model_steps: int) -> int:
        prime = self.prime(model_steps)
        every = self.recompute_every or model_steps - prime
        if not 1 <= every <= model_steps - prime:
            raise ValueError(
                f"recompute_every={every} must be in 1..{model_steps - prime} "
                f"(the model's {model_steps} steps minus prime_steps={prime})"
            )
        return every


@dataclass
class _Window:
    """One subset rank across rollouts: model context, cache and agent slots."""

    slots: np.ndarray  # [R, A] agent indices (-1 padding)
    start: int  # s0: step of the initial states
    cache: object
    agents: torch.Tensor  # agent embeddings [R, A, C]
    kind: torch.Tensor  # [R, A]
    decoded: int  # positions already in the cache


class RolloutEngine:
    """Steps a scene forward one timestep at a time for ``R`` rollouts (see the module docstring)."""

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
        config: SamplingConfig = SamplingConfig(),
    ):
        self.model = ckpt.model.eval()
        self.vocab = ckpt.vocabulary
        self.cfg = self.model.cfg
        self.sc = scenario
        self.config = config
        self.every = config.every(self.cfg.steps)
        self.prime = config.prime(self.cfg.steps)
        n = scenario.num_agents
        self.current = scenario.current_index if current_index is None else int(current_index)
        if not 0 <= self.current < scenario.num_steps:
            raise ValueError(f"current_index {self.current} out of range for {scenario.num_steps} steps")
        self.controlled = _agent_mask(controlled, n, "controlled")
        self.external = _agent_mask(external, n, "external") if external is not None else np.zeros(n, bool)
        if (self.controlled & self.external).any():
            raise ValueError(
                f"agents {np.flatnonzero(self.controlled & self.external).tolist()} are both controlled "
                "and external"
            )
        missing = np.flatnonzero(self.controlled & ~scenario.valid[:, self.current])
        if len(missing):
            raise ValueError(
                f"controlled agents must be valid at the current step {self.current}; track ids "
                f"{scenario.track_id[missing].tolist()} are not"
            )
        self.replay = ~(self.controlled | self.external)
        self.priority = np.zeros(n) if priority is None else np.asarray(priority, dtype=np.float64)
        self.R, self.N = int(rollouts), n
        self.T = self.current + 1 + int(horizon)
        self.generator = torch.Generator().manual_seed(int(config.seed))
        self.chunks: MapChunks = chunk_map(scenario, self.cfg.points_per_polyline)
        self._init_state()
        self.t = self.current
        self.windows: list[_Window] = []
        self.plan: list[SubsetPlan] = []
        self._window_step = -1
        self._cursor = (0, 0)  # (subset rank, slot) of the next position to act at step t

    # ------------------------------------------------------------------ state
    def _init_state(self) -> None:
        sc, R, N, T = self.sc, self.R, self.N, self.T
        logged = np.zeros((N, T, 3))
        lvalid = np.zeros((N, T), dtype=bool)
        keep = min(T, sc.num_steps)
        logged[:, :keep] = sc.xyh[:, :keep]
        lvalid[:, :keep] = sc.valid[:, :keep]
        known_steps = np.arange(T) <= self.current
        # what is fixed before the rollout: everyone's history, replay agents' whole future
        fixed = lvalid & (known_steps[None] | self.replay[:, None])
        tok = tokenize(self.vocab, logged, fixed, sc.size, sc.kind.astype(np.int64))
        self.xyh = np.repeat(np.where(fixed[..., None], logged, 0.0)[None], R, 0)
        self.valid = np.repeat(fixed[None], R, 0)
        self.mxyh = np.repeat(np.nan_to_num(tok.xyh)[None], R, 0)  # the model's (tokenized) view
        self.tokens = np.repeat(tok.tokens[None], R, 0)  # [R,N,T-1]
        # controlled agents exist for the whole rollout; their future tokens are unknown
        self.known = np.ones((R, N, T - 1), dtype=bool)  # a token is decided (a value, or -1 unobserved)
        self.known[:, self.controlled, self.current :] = False
        self.known[:, self.external, self.current :] = False
        self.valid[:, self.controlled, self.current :] = True

    # ------------------------------------------------------------------ windows
    def _build_windows(self) -> None:
        """Plan subsets per rollout at step ``t`` and encode each subset rank as one batched context."""
        t, A = self.t, self.cfg.max_agents
        s0 = max(0, t - self.prime)
        active = self.valid[:, :, t]
        plans = [
            plan_subsets(self.mxyh[r, :, t, :2], active[r], A, self.sc.sdc, self.priority)
            for r in range(self.R)
        ]
        k_max = max(p.num_subsets for p in plans)
        self.plan = plans
        self.windows = []
        for k in range(k_max):
            slots = np.full((self.R, A), -1, dtype=np.int64)
            for r, p in enumerate(plans):
                if k < p.num_subsets:
                    slots[r] = p.slots[k]
            scene = self._scene_inputs(slots, s0, [p.centres[min(k, p.num_subsets - 1)] for p in plans])
            cache, agents = self.model.start_decoding(scene, max_length=self.cfg.steps * A)
            self.windows.append(_Window(slots, s0, cache, agents, scene.agent_kind, 0))
        self._window_step = t
        self._prime(t)

    def _scene_inputs(self, slots: np.ndarray, s0: int, centres: list[int]) -> SceneInputs:
        R, c = self.R, self.cfg
        real = slots >= 0
        idx = np.where(real, slots, 0)
        r_ix = np.arange(R)[:, None]
        # initial state: the model's view at s0, or the first valid step after it (agents that appeared later)
        seg = self.valid[r_ix, idx, s0 : self.t + 1]  # [R,A,S]
        first = np.argmax(seg, axis=-1) + s0
        init = self.mxyh[r_ix, idx, first]
        frames = np.stack(
            [self.mxyh[r, centres[r], max(s0, _first_valid(self.valid[r, centres[r]], s0))] for r in range(R)]
        )
        local = to_local(frames[:, None, :], init)
        pts = np.zeros((R, c.max_polylines, c.points_per_polyline, 2), dtype=np.float32)
        pmask = np.zeros(pts.shape[:3], dtype=bool)
        mkind = np.zeros((R, c.max_polylines), dtype=np.int64)
        mmask = np.zeros((R, c.max_polylines), dtype=bool)
        for r in range(R):
            pts[r], pmask[r], mkind[r], mmask[r] = nearest_chunks(
                self.chunks, frames[r], c.max_polylines, MAP_RADIUS
            )
        return SceneInputs(
            agent_xyh=torch.from_numpy(np.where(real[..., None], local, 0.0)).float(),
            agent_size=torch.from_numpy(np.where(real[..., None], self.sc.size[idx], 1.0)).float(),
            agent_kind=torch.from_numpy(np.where(real, self.sc.kind[idx], 0).astype(np.int64)),
            agent_mask=torch.from_numpy(real),
            map_points=torch.from_numpy(pts),
            map_point_mask=torch.from_numpy(pmask),
            map_kind=torch.from_numpy(mkind),
            map_mask=torch.from_numpy(mmask),
        )

    def _joint(self, w: _Window, step: int, slots: list[int]) -> torch.Tensor:
        """Joint ids ``[R, len(slots)]`` of the tokens at ``step`` of the given slots (-1 unknown/absent)."""
        idx = w.slots[:, slots]
        tok = self.tokens[np.arange(self.R)[:, None], np.maximum(idx, 0), step]
        known = self.known[np.arange(self.R)[:, None], np.maximum(idx, 0), step]
        tok = np.where((idx >= 0) & known & (step >= w.start), tok, -1)
        # tokens before the agent's first valid step in the window are unobserved
        local = torch.from_numpy(tok)
        return self.model.global_ids(local, w.kind[:, slots])

    def _carried(self, w: _Window, positions: range) -> torch.Tensor:
        A = self.cfg.max_agents
        cols = []
        for p in positions:
            q = carried_position(self.cfg.variant, p, A)
            if q < 0:
                cols.append(torch.full((self.R,), START, dtype=torch.long))
            else:
                tau, slot = divmod(q, A)
                cols.append(self._joint(w, w.start + tau, [slot])[:, 0])
        return torch.stack(cols, 1)

    def _own(self, w: _Window, positions: range) -> torch.Tensor:
        """Joint ids ``[R, n]`` of each position's own agent token one step earlier (-1 at the first step)."""
        A = self.cfg.max_agents
        cols = []
        for p in positions:
            tau, slot = divmod(p, A)
            if tau == 0:
                cols.append(torch.full((self.R,), -1, dtype=torch.long))
            else:
                cols.append(self._joint(w, w.start + tau - 1, [slot])[:, 0])
        return torch.stack(cols, 1)

    def _prime(self, t: int) -> None:
        """Feed every window the known tokens of steps ``s0 .. t-1`` (teacher forcing, one chunk)."""
        A = self.cfg.max_agents
        for w in self.windows:
            n = (t - w.start) * A
            if n:
                positions = range(0, n)
                kinds = w.kind[:, [p % A for p in positions]]
                self.model.decode(
                    w.cache, w.agents, kinds, self._carried(w, positions), self._own(w, positions)
                )
                w.decoded = n

    # ------------------------------------------------------------------ stepping
    def needs_windows(self) -> bool:
        return (
            not self.windows or (self.t - self._window_step) % self.every == 0 and self.t != self._window_step
        )

    def step(self) -> None:
        """Advance all rollouts from ``t`` to ``t + 1`` (no external agents may be waiting)."""
        pending = self.advance()
        if pending is not None:
            raise RuntimeError(f"external agent {pending} must be supplied before the step can finish")

    def advance(self, stop_at: int | None = None) -> int | None:
        """Act positions of step ``t`` in order; returns an external agent whose next state is needed
        (supply it with :meth:`supply`, then call again), or None when the step is complete."""
        if self.t >= self.T - 1:
            raise RuntimeError(f"rollout horizon reached (step {self.t} of {self.T - 1})")
        if self.needs_windows():
            self._build_windows()
            self._cursor = (0, 0)
        A = self.cfg.max_agents
        trajeglish = self.cfg.variant is Variant.TRAJEGLISH
        while self._cursor[0] < len(self.windows):
            k, slot = self._cursor
            w = self.windows[k]
            tau = self.t - w.start
            chunk = range(slot, slot + 1) if trajeglish else range(0, A)
            waiting = self._waiting_external(w, list(chunk))
            if waiting is not None:
                return waiting
            positions = range(tau * A + chunk.start, tau * A + chunk.stop)
            logits = self.model.decode(
                w.cache,
                w.agents,
                w.kind[:, list(chunk)],
                self._carried(w, positions),
                self._own(w, positions),
            )
            w.decoded = positions.stop
            self._sample(w, list(chunk), logits)
            slot = chunk.stop
            self._cursor = (k + 1, 0) if slot >= A else (k, slot)
        late = self._unsupplied_external()
        if late is not None:
            return late
        self._finish_step()
        return None

    def _unsupplied_external(self) -> int | None:
        """An external agent alive at ``t`` whose next state has not been supplied yet (acting order)."""
        need = self.external[None] & ~self.known[:, :, self.t] & self.valid[:, :, self.t]
        agents = np.flatnonzero(need.any(0))
        if len(agents) == 0:
            return None
        return int(agents[np.argmin(self.priority[agents], kind="stable")])

    def _waiting_external(self, w: _Window, chunk: list[int]) -> int | None:
        idx = w.slots[:, chunk]
        r_ix = np.arange(self.R)[:, None]
        safe = np.maximum(idx, 0)
        need = (
            (idx >= 0)
            & self.external[safe]
            & ~self.known[r_ix, safe, self.t]
            & self.valid[r_ix, safe, self.t]
        )
        if self.cfg.variant is not Variant.TRAJEGLISH:
            return None  # other variants never see this step's tokens: externals may act after the model
        return int(idx[need][0]) if need.any() else None

    def _sample(self, w: _Window, chunk: list[int], logits: torch.Tensor) -> None:
        idx = w.slots[:, chunk]
        r_ix = np.arange(self.R)[:, None]
        safe = np.maximum(idx, 0)
        todo = (idx >= 0) & self.controlled[safe] & ~self.known[r_ix, safe, self.t]
        if not todo.any():
            return
        drawn = sample_logits(logits, self.config.temperature, self.config.top_p, self.generator).numpy()
        rr, cc = np.nonzero(todo)
        agents = idx[rr, cc]
        tok = drawn[rr, cc]
        self.tokens[rr, agents, self.t] = tok
        self.known[rr, agents, self.t] = True
        base = self.mxyh[rr, agents, self.t]
        nxt = to_global(base, self.vocab.templates[self.sc.kind[agents], tok])
        self.mxyh[rr, agents, self.t + 1] = nxt
        self.xyh[rr, agents, self.t + 1] = nxt
        self.valid[rr, agents, self.t + 1] = True

    def supply(self, agent: int, next_xyh: np.ndarray, valid: bool | np.ndarray = True) -> None:
        """Set the state at ``t + 1`` of external ``agent`` for every rollout (``next_xyh [R,3]``)."""
        if not self.external[agent]:
            raise ValueError(f"agent {agent} (track {self.sc.track_id[agent]}) is not external")
        next_xyh = np.broadcast_to(np.asarray(next_xyh, dtype=np.float64), (self.R, 3))
        ok = np.broadcast_to(np.asarray(valid, dtype=bool), (self.R,)) & self.valid[:, agent, self.t]
        t = self.t
        self.xyh[:, agent, t + 1] = np.where(ok[:, None], next_xyh, 0.0)
        self.valid[:, agent, t + 1] = ok
        pair = np.stack([self.mxyh[:, agent, t], next_xyh], 1)[:, None]  # [R,1,2,3]
        pv = np.stack([ok, ok], 1)[:, None]
        tok = tokenize(
            self.vocab,
            pair,
            pv,
            np.broadcast_to(self.sc.size[agent], (self.R, 1, 2)).copy(),
            np.full((self.R, 1), self.sc.kind[agent], dtype=np.int64),
        )
        self.tokens[:, agent, t] = np.where(ok, tok.tokens[:, 0, 0], -1)
        # the model's view of the agent is its tokenized state (re-anchored on the true state after a gap)
        self.mxyh[:, agent, t + 1] = np.where(ok[:, None], np.nan_to_num(tok.xyh[:, 0, 1]), 0.0)
        self.known[:, agent, t] = True

    def _finish_step(self) -> None:
        self.known[:, :, self.t] = True  # whatever was not decided is unobserved from now on
        self.t += 1
        self._cursor = (0, 0)

    # ------------------------------------------------------------------ whole rollouts
    def run(self) -> None:
        """Step until the horizon (no external agents)."""
        while self.t < self.T - 1:
            self.step()


def _agent_mask(mask: np.ndarray, n: int, name: str) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.dtype != np.bool_ or mask.shape != (n,):
        raise ValueError(
            f"{name}: expected a bool mask of shape ({n},) (one entry per agent), "
            f"got {mask.dtype} {mask.shape}"
        )
    return mask


def _first_valid(valid: np.ndarray, start: int) -> int:
    hits = np.flatnonzero(valid[start:])
    return start + int(hits[0]) if len(hits) else start
