"""NPC drivers over the B scene rows of a :class:`~trajeglish_env.env.scene_batch.SceneBatch`: they walk
each row's intra-timestep order, let the NPCs act, and pause wherever an external agent's next state is
needed (``advance`` hands those agents out, ``supply`` takes their states).

:class:`EngineRows` runs the Trajeglish model (one :class:`~trajeglish_env.sampler.engine.BatchEngine`
row per scene, one model call per token position for all rows); :class:`RuleRows` runs a rule-based
:class:`~trajeglish_env.env.npc.NPCPolicy` per scene (:class:`OrderedDriver`). Both expose a row's exact
states through :meth:`view` (a :class:`RowView`).
"""

from __future__ import annotations

import copy
import functools
import warnings
import weakref
from collections.abc import Callable
from typing import ClassVar, Protocol

import numpy as np

from trajeglish_env.env.npc import NPCPolicy
from trajeglish_env.env.world import WorldView
from trajeglish_env.scenario import Scenario, agent_name

Waiting = tuple[np.ndarray, np.ndarray]  # (rows, agents): one external agent per row whose state is needed


class RowView(Protocol):
    """One scene row: exact states ``xyh [N,T,3]`` / ``valid [N,T]`` (T = current + 1 + horizon), the step
    ``t`` being played, who has ``moved`` in it, and the external agents still to act, in order."""

    @property
    def xyh(self) -> np.ndarray:
        """Exact states ``[N,T,3]`` of the row's agents."""

    @property
    def valid(self) -> np.ndarray:
        """``[N,T]``: where the states exist."""

    @property
    def t(self) -> int:
        """The step being played."""

    def moved(self) -> np.ndarray:
        """``[N]``: the agents that have moved in this step so far."""

    def external_order(self) -> np.ndarray:
        """The external agents still to act in this step, in acting order."""


class NPCRows(Protocol):
    """What a scene batch needs from its NPC driver (rows are scenes)."""

    def start(
        self,
        row: int,
        scenario: Scenario,
        external: np.ndarray,
        horizon: int,
        priority: np.ndarray,
        seed: int,
    ) -> RowView:
        """(Re)start ``row`` on ``scenario`` for an episode; returns the row's view."""

    def stop(self, row: int) -> None:
        """Take ``row`` out of the simulation."""

    def advance(self) -> Waiting | None:
        """Let NPCs act up to the next external agents (which rows wait on whom), or None at a step's end."""

    def supply(self, rows: np.ndarray, agents: np.ndarray, next_xyh: np.ndarray, valid: np.ndarray) -> None:
        """The external agents' next states, for the rows waiting on them."""


def first_agent(priority: np.ndarray, active: np.ndarray) -> int:
    """The active agent acting first (lowest priority; lowest index on ties)."""
    act = np.flatnonzero(active)
    return int(act[np.argmin(priority[act])])


class OrderedDriver:
    """Rule-based NPCs of one scene: agents act by (priority, distance to the first agent); consecutive NPCs
    act as one vectorized group; agents that are neither NPC nor external follow the log (fixed in advance).
    """

    def __init__(
        self,
        policy: NPCPolicy,
        scenario: Scenario,
        external: np.ndarray,
        horizon: int,
        priority: np.ndarray,
        seed: int,
    ):
        sc, cur = scenario, scenario.current_index
        n, self.T = sc.num_agents, cur + 1 + int(horizon)
        self.scenario, self.policy, self.priority = sc, policy, np.asarray(priority, dtype=np.float64)
        self.external = np.asarray(external, dtype=bool)
        self.npc = sc.valid[:, cur] & ~self.external
        self.xyh = np.zeros((n, self.T, 3))
        self.valid = np.zeros((n, self.T), dtype=bool)
        keep = min(self.T, sc.num_steps)
        fixed = sc.valid[:, :keep] & ((np.arange(keep) <= cur)[None] | ~(self.npc | self.external)[:, None])
        self.xyh[:, :keep] = np.where(fixed[..., None], sc.xyh[:, :keep], 0.0)
        self.valid[:, :keep] = fixed
        policy.reset(sc, self.npc.copy(), cur, int(seed))
        self._t = cur
        self._begin()

    @property
    def t(self) -> int:
        """The current step (the one being played: from ``t`` to ``t + 1``)."""
        return self._t

    def _begin(self) -> None:
        t = self._t
        if t == self.scenario.num_steps - 1 and self.T > self.scenario.num_steps:
            self.npc |= self.valid[:, t] & ~self.external  # the log ends: its agents go on as NPCs
        acting = (self.npc | self.external) & self.valid[:, t]
        agents = np.flatnonzero(acting)
        if len(agents):
            lead = first_agent(self.priority, acting)
            dist = np.linalg.norm(self.xyh[agents, t, :2] - self.xyh[lead, t, :2], axis=-1)
            agents = agents[np.lexsort((dist, self.priority[agents]))]
        self.order = agents
        self.known = ~acting
        self.cursor = 0

    def moved(self) -> np.ndarray:
        """``[N]`` agents whose next state is already decided in this step."""
        return self.known & self.valid[:, self._t]

    def external_order(self) -> np.ndarray:
        """External agents still to act this step, in order."""
        rest = self.order[self.cursor :]
        return rest[self.external[rest] & ~self.known[rest]]

    def advance(self) -> int | None:
        """Let NPCs act until an external agent's turn (returned) or the end of the step (None)."""
        if self._t >= self.T - 1:
            raise RuntimeError(f"episode horizon reached (step {self._t} of {self.T - 1})")
        order = self.order
        while self.cursor < len(order):
            pending = np.flatnonzero(~self.known[order[self.cursor :]])
            if not len(pending):  # everyone left has moved
                self.cursor = len(order)
                break
            self.cursor += int(pending[0])
            a = int(order[self.cursor])
            if self.external[a]:
                return a
            tail = order[self.cursor :]  # the group: consecutive NPCs still to move
            stops = np.flatnonzero(~self.npc[tail] | self.known[tail])
            end = self.cursor + (int(stops[0]) if len(stops) else len(tail))
            group = order[self.cursor : end]
            view = WorldView(
                self.scenario, self.xyh, self.valid, self._t, self.moved(), self.external, self.npc
            )
            nxt, ok = self.policy.act(view, group)
            nxt, ok = np.asarray(nxt, dtype=np.float64), np.asarray(ok, dtype=bool)
            name = type(self.policy).__name__
            if nxt.shape != (len(group), 3) or ok.shape != (len(group),):
                raise ValueError(
                    f"NPC policy {name}.act must return next states [{len(group)},3] and validity "
                    f"[{len(group)}], got {nxt.shape} / {ok.shape} (step {self._t})"
                )
            bad = np.flatnonzero(ok & ~np.isfinite(nxt).all(axis=1))
            if len(bad):
                who = agent_name(self.scenario.kind[group[bad[0]]], self.scenario.track_id[group[bad[0]]])
                raise ValueError(
                    f"NPC policy {name}.act returned a non-finite next state {nxt[bad[0]].tolist()} for "
                    f"{who} at step {self._t} ({len(bad)} agent(s)); states marked valid must be finite"
                )
            self.xyh[group, self._t + 1] = np.where(ok[:, None], nxt, 0.0)
            self.valid[group, self._t + 1] = ok
            self.known[group] = True
            self.cursor = end
        self._t += 1
        self._begin()
        return None

    def supply(self, agent: int, next_xyh: np.ndarray, valid: bool = True) -> None:
        """Set an external agent's next state (``valid=False``: it leaves the scene)."""
        if not self.external[agent]:
            raise ValueError(f"agent {agent} (track {self.scenario.track_id[agent]}) is not external")
        self.xyh[agent, self._t + 1] = next_xyh if valid else 0.0
        self.valid[agent, self._t + 1] = bool(valid) and self.valid[agent, self._t]
        self.known[agent] = True


class PolicyCopies:
    """The policy of each scene slot of an env given a user's NPC policy object: the object itself for the
    first slot, while no other env's slot plays it (its counters and logs see the episodes, as before), and
    a ``copy.deepcopy`` for every other slot (other scenes of a batch, other envs): one object shared by
    several slots had each reset overwrite another scene's episode state. An object that cannot be copied
    (a lock, a client) is shared, with a warning."""

    _players: ClassVar[dict[int, weakref.ref]] = {}  # id(object) -> the PolicyCopies whose slot plays it

    def __init__(self, npc: NPCPolicy):
        self.npc = npc
        self._gave_original = False

    def __call__(self) -> NPCPolicy:
        key = id(self.npc)
        player = PolicyCopies._players.get(key)
        if not self._gave_original and (player is None or player() is None):
            PolicyCopies._players[key] = weakref.ref(self, functools.partial(_release, key))
            self._gave_original = True
            return self.npc
        try:
            return copy.deepcopy(self.npc)
        except Exception as error:  # noqa: BLE001 (any failure to copy: share instead, and say so)
            warnings.warn(
                f"NPC policy {type(self.npc).__name__}: cannot be copied ({error}); the scenes share the one "
                "object, so each one's reset overwrites the others' episode state (give each env its own, or "
                "let it deep-copy)",
                stacklevel=2,
            )
            return self.npc

    def __getstate__(self) -> dict[str, object]:
        return {"npc": self.npc, "_gave_original": False}  # another process: its own first slot


def _release(key: int, ref: weakref.ref) -> None:
    """A :class:`PolicyCopies` whose slot played an object is gone: another env's slot may play it."""
    if PolicyCopies._players.get(key) is ref:
        del PolicyCopies._players[key]


class RuleRows:
    """Rule-based NPCs of B scenes, one :class:`OrderedDriver` (and policy object) per row: a row's step is
    complete when its driver has walked its order; :meth:`advance` returns None once every row that takes
    part in the step is complete (rows wait for each other, as in the engine)."""

    def __init__(self, rows: int, make_policy: Callable[[], NPCPolicy], fresh_each_start: bool = True):
        self.drivers: list[OrderedDriver | None] = [None] * rows
        self.make_policy = make_policy
        # False: one policy per row, made at its first start and reset at every later one (a user's object,
        # copied once per row: its copy may be costly, and its reset() starts each episode)
        self.fresh_each_start = fresh_each_start
        self._policies: list[NPCPolicy | None] = [None] * rows
        self._complete: set[int] = set()

    def start(
        self,
        row: int,
        scenario: Scenario,
        external: np.ndarray,
        horizon: int,
        priority: np.ndarray,
        seed: int,
    ) -> RowView:
        """(Re)start ``row`` on a scene (rows are independent: any time)."""
        self._complete.discard(row)
        policy = self._policies[row]
        if policy is None or self.fresh_each_start:
            policy = self._policies[row] = self.make_policy()
        self.drivers[row] = OrderedDriver(policy, scenario, external, horizon, priority, seed)
        return self.drivers[row]

    def stop(self, row: int) -> None:
        """Take ``row`` out until it is started again."""
        self.drivers[row] = None
        self._complete.discard(row)

    def advance(self) -> Waiting | None:
        """Let every stepping row's NPCs act up to its next external agent; None once every row has
        finished the step."""
        rows, agents = [], []
        stepping = [r for r, d in enumerate(self.drivers) if d is not None and d.t < d.T - 1]
        for r in stepping:
            if r in self._complete:
                continue
            agent = self.drivers[r].advance()  # type: ignore[union-attr]
            if agent is None:
                self._complete.add(r)
            else:
                rows.append(r)
                agents.append(agent)
        if rows:
            return np.array(rows, dtype=np.int64), np.array(agents, dtype=np.int64)
        self._complete.clear()
        return None

    def supply(self, rows: np.ndarray, agents: np.ndarray, next_xyh: np.ndarray, valid: np.ndarray) -> None:
        """Set the next states of external ``agents`` of ``rows``."""
        for r, a, x, ok in zip(rows.tolist(), agents.tolist(), next_xyh, valid.tolist(), strict=True):
            self.drivers[r].supply(a, x, ok)  # type: ignore[union-attr]


class EngineRow:
    """Row ``row`` of a :class:`EngineRows` as a :class:`RowView`."""

    def __init__(self, rows: EngineRows, row: int, scenario: Scenario, external: np.ndarray, horizon: int):
        self.engine, self.row, self.n = rows.engine, row, scenario.num_agents
        self.T = scenario.current_index + 1 + int(horizon)
        self.external = external
        self.priority = rows.engine.row_priority[row, : self.n].copy()
        self.ordered_in_slots = rows.ordered_in_slots

    @property
    def xyh(self) -> np.ndarray:
        """``[N, T, 3]`` exact states (a view of the engine's row)."""
        return self.engine.xyh[self.row, : self.n, : self.T]

    @property
    def valid(self) -> np.ndarray:
        """``[N, T]`` validity (a view of the engine's row)."""
        return self.engine.valid[self.row, : self.n, : self.T]

    @property
    def t(self) -> int:
        """The current step of the row."""
        return int(self.engine.now[self.row])

    def moved(self) -> np.ndarray:
        """``[N]`` agents whose token of this step is decided (log-replayed agents: always)."""
        t = self.t
        if t >= self.T - 1:  # the episode is over: nobody moves any more
            return np.zeros(self.n, dtype=bool)
        return self.engine.known[self.row, : self.n, t] & self.valid[:, t]

    def pending(self) -> np.ndarray:
        """External agents present at this step whose next state is not supplied yet."""
        t = self.t
        if t >= self.T - 1:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.external & ~self.engine.known[self.row, : self.n, t] & self.valid[:, t])

    def external_order(self) -> np.ndarray:
        """External agents still to act this step, in the order they will be asked for."""
        pending = self.pending()
        by_priority = pending[np.argsort(self.priority[pending], kind="stable")]
        plan = self.engine.plan[self.row]
        if not self.ordered_in_slots or plan is None:
            return by_priority
        planned = plan.acting_order[np.isin(plan.acting_order, pending)]
        return np.concatenate([planned, by_priority[~np.isin(by_priority, planned)]]).astype(np.int64)


class EngineRows:
    """Trajeglish NPCs of B scenes through one :class:`~trajeglish_env.sampler.engine.BatchEngine` (row i =
    scene i). With ``externals_first`` every external agent is asked for, in priority order, before any NPC
    decodes, so NPCs of every model context condition on them; otherwise external agents act at their place
    in the engine's acting order (priorities, then distance, per model context). With ``entering`` the
    agents the log brings in later are driven by the model from their first logged step."""

    def __init__(self, engine: object, externals_first: bool, entering: bool = False):
        from trajeglish_env.model.config import Variant
        from trajeglish_env.sampler.engine import BatchEngine

        assert isinstance(engine, BatchEngine)
        self.engine = engine
        self.externals_first = externals_first
        self.entering = entering
        self.ordered_in_slots = engine.cfg.variant is Variant.TRAJEGLISH and not externals_first
        self.views: list[EngineRow | None] = [None] * engine.B

    def start(
        self,
        row: int,
        scenario: Scenario,
        external: np.ndarray,
        horizon: int,
        priority: np.ndarray,
        seed: int,
    ) -> RowView:
        """(Re)start engine row ``row`` on a scene (an unfinished step of the others is undone)."""
        from trajeglish_env.sampler.engine import RowSpec

        active = scenario.valid[:, scenario.current_index]
        spec = RowSpec(
            scenario,
            int(horizon),
            active & ~external,
            external,
            priority=priority,
            first=first_agent(priority, active),  # the first model context: the agent acting first
            entering=self.entering,
        )
        self.engine.start_rows([row], spec, [seed])
        view = self.views[row] = EngineRow(self, row, scenario, external, horizon)
        return view

    def stop(self, row: int) -> None:
        """Take ``row`` out until it is started again."""
        self.engine.stop_rows([row])
        self.views[row] = None

    def advance(self) -> Waiting | None:
        """Decode NPCs until every stepping row waits for an external agent (the first of each row is
        returned) or the step is complete (None; also when no row is stepping)."""
        if not self.engine.stepping.any():
            return None
        if self.externals_first:
            e = self.engine
            b, t = np.arange(e.B), np.minimum(e.now, e.T - 2)
            need = e.row_external & ~e.known[b, :, t] & e.valid[b, :, t] & e.stepping[:, None]
            rows = np.flatnonzero(need.any(axis=1))
            if len(rows):  # lowest priority first, lowest index on ties
                agents = np.argmin(np.where(need[rows], e.row_priority[rows], np.inf), axis=1)
                return rows, agents.astype(np.int64)
        waiting = self.engine.advance()
        if waiting is None:
            return None
        rows, first = np.unique(waiting[0], return_index=True)  # late externals come several per row
        return rows, waiting[1][first]

    def supply(self, rows: np.ndarray, agents: np.ndarray, next_xyh: np.ndarray, valid: np.ndarray) -> None:
        """Set the next states of external ``agents`` of ``rows``; the model sees them tokenized."""
        self.engine.supply(rows, agents, next_xyh, valid)
