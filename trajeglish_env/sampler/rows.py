"""Per-row state of :class:`~trajeglish_env.sampler.engine.BatchEngine`: what each row simulates, its
exact and tokenized states, and how rows are (re)started, stopped, fed the states of external agents and
given the agents the log brings in later.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from trajeglish_env.batch_geometry import edge_rows, road_edges
from trajeglish_env.scenario import Scenario, agent_name
from trajeglish_env.tokenizer.tokenize import tokenize, tokenize_moves
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

# A row's road edges as :func:`~trajeglish_env.batch_geometry.edge_rows` gives them: columns [7,S]
# (float32) and links [3,S] (int64); S = 0 for a row without road edges (or not started).
RowEdges = tuple[np.ndarray, np.ndarray]
NO_EDGES: RowEdges = (np.zeros((7, 0), np.float32), np.zeros((3, 0), np.int64))
# An external agent whose tokenized state (the model's view of it) is farther than this (m, mean corner
# distance) from its true state moves beyond what the vocabulary can follow: warned once per row start.
DRIFT_WARN_M = 0.5


@dataclass(frozen=True)
class RowSpec:
    """What one row simulates: ``controlled [N]`` agents the model drives, ``external [N]`` agents whose
    states are supplied from outside (others replay the log), ``horizon`` steps after ``current_index``
    (default: the scene's), acting ``priority [N]`` (lower first), and ``first``: the agent whose model
    context goes first (default: the sdc). ``entering``: the agents the log brings in after the current
    step are driven by the model from their first logged step on (they enter where and as the log has
    them) instead of replaying the log, which cannot react to the agents around them."""

    scenario: Scenario
    horizon: int
    controlled: np.ndarray
    external: np.ndarray | None = None
    current_index: int | None = None
    priority: np.ndarray | None = None
    first: int | None = None
    entering: bool = False


class RowStates:
    """The per-row arrays of ``rows`` rows, padded to the largest scene: ``N`` agents, ``T`` steps.

    Exact states ``xyh [B,N,T,3]`` and ``valid [B,N,T]``; the model's tokenized view ``mxyh``;
    ``tokens [B,N,T-1]`` and ``known`` (the token of a step is decided); the agents' roles ``row_*``;
    ``now [B]`` the step being played and ``end [B]`` the last step.
    """

    def __init__(self, rows: int, vocab: MotionVocabulary):
        self.vocab = vocab
        self.B = int(rows)
        self.N, self.T = 0, 2
        self._allocate(1, 2)
        self.live = np.zeros(self.B, dtype=bool)
        self.now = np.zeros(self.B, dtype=np.int64)
        self.end = np.zeros(self.B, dtype=np.int64)
        self.seed = np.zeros(self.B, dtype=np.uint64)
        self.first = np.zeros(self.B, dtype=np.int64)
        self.handover_step = np.full(self.B, -1, dtype=np.int64)  # where a row's log ends (past it: -1)
        self.scenes: list[Scenario | None] = [None] * self.B
        self.with_edges = False  # engines that need the rows' road edges (guarded sampling) set this
        self.edges: list[RowEdges] = [NO_EDGES] * self.B
        self._edge_cache: dict[int, tuple[Scenario, RowEdges]] = {}
        self._in_step = False  # a step has begun and is not finished (see cancel_step)
        self._supplied: list[tuple[np.ndarray, ...]] = []  # supplies whose tokens are not computed yet
        self.drift_tolerance = DRIFT_WARN_M
        self._drift_warned: set[tuple[int, int]] = set()  # (row, agent) warned since the row's start
        # drafted tokens [B,N] of the step being decoded in parallel (None: sequential decoding)
        self._draft: np.ndarray | None = None
        self._ahead: np.ndarray | None = None  # drafts [B,N] for the next step, drawn looking ahead
        self._ahead_rank = np.zeros((0, 0), np.int64)  # [B,N] the subset rank that drew each of them
        # [B,N,V] the class logits each agent's last token was drawn from in parallel, and [B,N] its step
        self._drawn_logits = np.zeros((0, 0, 0), np.float32)
        self._drawn_at = np.zeros((0, 0), np.int64)
        self._ahead_logits = np.zeros((0, 0, 0), np.float32)  # [B,N,V] those the look-ahead drew from

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
        self.acting_rank = grow(get("acting_rank"), (B, n), -1, np.int64)  # place in the step (-1: none)
        self.handover = grow(get("handover"), (B, n), False, bool)
        self.entering = grow(get("entering"), (B, n), False, bool)
        self.size = grow(get("size"), (B, n, 2), 1.0, np.float64)
        self.kind = grow(get("kind"), (B, n), 0, np.int64)
        self.N, self.T = n, t

    def start_rows(self, rows: np.ndarray | list[int], spec: RowSpec, seeds: np.ndarray | list[int]) -> None:
        """(Re)start ``rows`` on ``spec``, row ``rows[i]`` drawing from ``seeds[i]`` (an unfinished step of
        the other rows is undone, see :meth:`cancel_step`)."""
        self.cancel_step()
        self._tokenize_supplied()
        self._draft = self._ahead = None
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        seeds = np.asarray(seeds, dtype=np.uint64).reshape(-1)
        if len(self._drawn_at):
            self._drawn_at[rows[(rows >= 0) & (rows < self.B)]] = -1  # a restarted row drafts afresh
        if len(rows) != len(seeds) or ((rows < 0) | (rows >= self.B)).any():
            raise ValueError(
                f"start_rows: {len(rows)} rows in 0..{self.B - 1} need as many seeds, got {seeds}"
            )
        restarted = set(rows.tolist())
        self._drift_warned = {k for k in self._drift_warned if k[0] not in restarted}
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
        self.acting_rank[rows] = -1  # set when the rows' model contexts are planned
        # a rollout past the log: the log's agents present at its last step go on as controlled agents
        self.handover[rows] = False
        if T > sc.num_steps:
            self.handover[rows, :n] = replay & sc.valid[:, -1]
        self.handover_step[rows] = sc.num_steps - 1 if T > sc.num_steps else -1
        # agents the log brings in later: handed to the model at their first logged step (spec.entering)
        self.entering[rows] = False
        if spec.entering:
            later = lvalid[:, cur + 1 : T - 1].any(axis=1) & ~lvalid[:, cur]
            self.entering[rows, :n] = replay & later
        self.size[rows] = 1.0
        self.size[rows, :n] = sc.size
        self.kind[rows] = 0
        self.kind[rows, :n] = sc.kind
        edges = self._road_edges(sc) if self.with_edges else NO_EDGES
        for r in rows:
            self.scenes[r] = sc
            self.edges[r] = edges
        self.now[rows], self.end[rows] = cur, T - 1
        self.seed[rows] = seeds
        self.first[rows] = sc.sdc if spec.first is None else int(spec.first)
        self.live[rows] = True

    def _hand_over_entering(self, stepping: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Agents of ``entering`` rows at their first logged step become controlled (the model drives them
        from this step on, as at the log's end); returns them as ``(rows, agents)``."""
        rows = np.flatnonzero(stepping)
        now = self.now[rows]
        arrived = self.entering[rows] & self.valid[rows, :, now]
        r, a = np.nonzero(arrived)
        if not len(r):
            return r, a
        rows = rows[r]
        self.entering[rows, a] = False
        self.row_controlled[rows, a] = True
        span = np.arange(self.T)[None, :]
        future = (span >= self.now[rows, None]) & (span <= self.end[rows, None])
        self.known[rows, a] &= ~future[:, : self.T - 1]
        self.valid[rows, a] |= future & (span > self.now[rows, None])
        return rows, a

    def _delay_blocked_entries(self, rows: np.ndarray) -> None:
        """Entering agents whose box, where the log brings them in at the next step, would overlap an agent
        there enter a step later (at the same place; again until it is clear; not at all if the rollout
        ends first)."""
        t1 = self.now[rows] + 1
        live = t1 < self.T
        rows, t1 = rows[live], t1[live]
        if not len(rows):
            return
        entry = self.entering[rows] & self.valid[rows, :, t1] & ~self.valid[rows, :, t1 - 1]
        r, a = np.nonzero(entry)
        if not len(r):
            return
        from trajeglish_env.metrics.boxes import box_collisions

        rr, tt = rows[r], t1[r]
        others = self.valid[rr, :, tt].copy()  # [k, N] every agent present there, the agent itself not
        others[np.arange(len(r)), a] = False
        k, b = np.nonzero(others)
        hit = box_collisions(
            self.xyh[rr[k], a[k], tt[k]],
            self.size[rr[k], a[k]],
            self.xyh[rr[k], b, tt[k]],
            self.size[rr[k], b],
        )
        blocked = np.zeros(len(r), bool)
        blocked[k[hit]] = True
        rr, a, tt = rr[blocked], a[blocked], tt[blocked]
        later = tt + 1 < self.T  # at the rollout's last step a blocked agent does not enter at all
        for arr in (self.xyh, self.mxyh):
            arr[rr[later], a[later], tt[later] + 1] = arr[rr[later], a[later], tt[later]]
            arr[rr, a, tt] = 0.0
        self.valid[rr[later], a[later], tt[later] + 1] = True
        self.valid[rr, a, tt] = False
        self.tokens[rr[later], a[later], tt[later]] = -1

    def guard_moved(self, rows: np.ndarray, agents: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``[n,N]``: the agents whose next state the guard of agent ``agents[i]`` of row ``rows[i]`` at step
        ``t[i]`` sees: those whose token of the step is decided, but not the logged (replay) agents acting
        after it -- their log is known ahead, yet the step's order hides their move (the model does not see
        it either), so the guard sees their current boxes, as it does for an agent that has not moved."""
        moved = self.known[rows, :, t].copy()
        rank = self.acting_rank[rows]
        own = rank[np.arange(len(rows)), agents][:, None]
        replay = ~(self.row_controlled[rows] | self.row_external[rows])
        moved &= ~(replay & (rank > own) & (own >= 0))
        return moved

    def _road_edges(self, sc: Scenario) -> RowEdges:
        """The scene's road-edge segments (computed once per scene object, like the map chunks)."""
        hit = self._edge_cache.get(id(sc))
        if hit is None or hit[0] is not sc:
            if len(self._edge_cache) > 4 * self.B + 64:
                self._edge_cache.clear()
            hit = (sc, edge_rows(road_edges(sc)))
            self._edge_cache[id(sc)] = hit
        return hit[1]

    def stop_rows(self, rows: np.ndarray | list[int]) -> None:
        """Take ``rows`` out of the simulation (they stop stepping until started again; an unfinished step
        of the others is undone, see :meth:`cancel_step`)."""
        self.cancel_step()
        self.live[np.asarray(rows, dtype=np.int64)] = False

    def cancel_step(self) -> None:
        """Undo the unfinished step of every stepping row: the tokens decoded or supplied in it are forgotten
        (decoding it again draws the same ones, and overwrites the same cache positions), so rows can be
        (re)started or stopped as between steps."""
        if not self._in_step:
            return
        self._supplied = []
        self._draft = self._ahead = None
        rows = np.flatnonzero(self.stepping)
        r, a = np.nonzero(self.row_controlled[rows] | self.row_external[rows])
        rr, t = rows[r], self.now[rows[r]]
        self.known[rr, a, t] = False
        self.tokens[rr, a, t] = -1
        ext = self.row_external[rr, a]
        self.valid[rr[ext], a[ext], t[ext] + 1] = False
        self.xyh[rr[ext], a[ext], t[ext] + 1] = 0.0
        self._in_step = False

    @property
    def stepping(self) -> np.ndarray:
        """``[B]`` rows that take part in the current step."""
        return self.live & (self.now < self.end)

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
        bad = ok & ~np.isfinite(next_xyh).all(axis=1)
        if bad.any():
            q = int(np.flatnonzero(bad)[0])
            b, a = int(rows[q]), int(agents[q])
            sc = self.scenes[b]
            name = (
                agent_name(sc.kind[a], sc.track_id[a])
                if sc is not None and a < sc.num_agents
                else f"agent {a}"
            )
            raise ValueError(
                f"supplied state of external {name} (agent index {a}) of row {b} at step {int(t[q]) + 1}: "
                f"expected finite x, y, heading, got {next_xyh[q].tolist()}"
            )
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
        if len(rows) > 1:  # an agent supplied twice before the call: its last supply counts
            _, last = np.unique((rows * self.N + agents)[::-1], return_index=True)
            keep = np.sort(len(rows) - 1 - last)
            rows, agents, t, nxt, ok = rows[keep], agents[keep], t[keep], nxt[keep], ok[keep]
        self.tokens[rows, agents, t] = -1
        self.mxyh[rows, agents, t + 1] = 0.0
        rows, agents, t, nxt = rows[ok], agents[ok], t[ok], nxt[ok]
        if not len(rows):
            return
        base = self.mxyh[rows, agents, t]
        tokens, states, error = tokenize_moves(
            self.vocab, base, nxt, self.size[rows, agents], self.kind[rows, agents]
        )
        self.tokens[rows, agents, t] = tokens
        self.mxyh[rows, agents, t + 1] = states
        drift = error > self.drift_tolerance
        if drift.any():
            self._warn_drift(rows[drift], agents[drift], error[drift], t[drift])

    def _warn_drift(self, rows: np.ndarray, agents: np.ndarray, error: np.ndarray, t: np.ndarray) -> None:
        """Warn once per row start and agent whose tokenized state drifts beyond ``drift_tolerance``."""
        for b, a, e, step in zip(rows.tolist(), agents.tolist(), error.tolist(), t.tolist(), strict=True):
            if (b, a) in self._drift_warned:
                continue
            self._drift_warned.add((b, a))
            sc = self.scenes[b]
            known = sc is not None and a < sc.num_agents
            name = agent_name(sc.kind[a], sc.track_id[a]) if known else f"agent index {a}"
            where = f"scene {sc.scenario_id!r}" if known else "its scene"
            warnings.warn(
                f"external agent {name} of {where} (batch row {b}): its tokenized state is {e:.2f} m from "
                f"its true state at step {step + 1} (> {self.drift_tolerance} m); it moves beyond what the "
                "motion vocabulary can follow (faster than its templates?); the NPCs see it where it is not",
                stacklevel=2,
            )


def _agent_mask(mask: np.ndarray, n: int, name: str) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.dtype != np.bool_ or mask.shape != (n,):
        raise ValueError(
            f"{name}: expected a bool mask of shape ({n},) (one entry per agent), "
            f"got {mask.dtype} {mask.shape}"
        )
    return mask
