"""Step drivers: walk one timestep's intra-timestep order, letting the NPCs act and pausing at every
external agent whose next state is needed (the engine's ``advance`` / ``supply`` protocol).

:class:`EngineDriver` runs the Trajeglish model (one token per NPC through the KV cache, any scene size);
:class:`OrderedDriver` runs a rule-based :class:`~trajeglish_env.env.npc.NPCPolicy` group by group. Both
expose the exact states ``xyh [N,T,3]`` / ``valid [N,T]`` (T = current + 1 + horizon), the step ``t``
and who has ``moved`` in it.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from trajeglish_env.env.npc import NPCPolicy
from trajeglish_env.env.world import WorldView
from trajeglish_env.scenario import Scenario


class StepDriver(Protocol):
    """What the environment needs from a driver."""

    xyh: np.ndarray
    valid: np.ndarray

    @property
    def t(self) -> int: ...

    def moved(self) -> np.ndarray: ...

    def advance(self) -> int | None: ...

    def supply(self, agent: int, next_xyh: np.ndarray, valid: bool = True) -> None: ...

    def external_order(self) -> np.ndarray: ...


def first_agent(priority: np.ndarray, active: np.ndarray) -> int:
    """The active agent acting first (lowest priority; lowest index on ties)."""
    act = np.flatnonzero(active)
    return int(act[np.argmin(priority[act])])


class OrderedDriver:
    """Rule-based NPCs: agents act by (priority, distance to the first agent); consecutive NPCs act as one
    vectorized group; agents that are neither NPC nor external follow the log (fixed in advance)."""

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
            a = int(order[self.cursor])
            if self.known[a]:
                self.cursor += 1
                continue
            if self.external[a]:
                return a
            end = self.cursor
            while end < len(order) and self.npc[order[end]] and not self.known[order[end]]:
                end += 1
            group = order[self.cursor : end]
            view = WorldView(
                self.scenario, self.xyh, self.valid, self._t, self.moved(), self.external, self.npc
            )
            nxt, ok = self.policy.act(view, group)
            nxt, ok = np.asarray(nxt, dtype=np.float64), np.asarray(ok, dtype=bool)
            if nxt.shape != (len(group), 3) or ok.shape != (len(group),) or not np.isfinite(nxt[ok]).all():
                raise ValueError(
                    f"NPC policy {type(self.policy).__name__}.act must return finite next states "
                    f"[{len(group)},3] and validity [{len(group)}], got {nxt.shape} / {ok.shape}"
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


class EngineDriver:
    """Trajeglish NPCs through one row of a :class:`~trajeglish_env.sampler.engine.BatchEngine`.

    By default the driver owns a one-row engine. With ``shared=(engine, row)`` the row belongs to an
    engine that a batched environment steps for all its scenes at once (its owner calls
    ``engine.step()`` after every scene has supplied its external agents; see
    :mod:`trajeglish_env.env.vector`), and :meth:`advance` then only reports what the owner has done.

    With ``externals_first`` every external agent acts before any NPC decodes (supplied up front, in
    priority order), so NPCs of every model context condition on them; otherwise external agents act at
    their place in the engine's acting order (priorities, then distance, per model context).
    """

    def __init__(
        self,
        ckpt: object,
        scenario: Scenario,
        external: np.ndarray,
        horizon: int,
        priority: np.ndarray,
        seed: int,
        settings: object = None,
        externals_first: bool = False,
        shared: tuple[object, int] | None = None,
    ):
        from trajeglish_env.env.config import TrajeglishNPC
        from trajeglish_env.model.config import Variant
        from trajeglish_env.sampler.engine import BatchEngine, RowSpec

        settings = settings if isinstance(settings, TrajeglishNPC) else TrajeglishNPC(ckpt)
        cur = scenario.current_index
        self.scenario = scenario
        self.external = np.asarray(external, dtype=bool)
        self.priority = np.asarray(priority, dtype=np.float64)
        self.externals_first = externals_first
        active = scenario.valid[:, cur]
        if shared is None:
            self.engine: BatchEngine = BatchEngine(
                ckpt,  # type: ignore[arg-type]
                1,
                settings.sampling(),
                settings.torch_cache_dtype,
            )
            self.row, self.shared = 0, False
        else:
            self.engine, self.row = shared  # type: ignore[assignment]
            self.shared = True
        spec = RowSpec(
            scenario,
            int(horizon),
            active & ~self.external,
            self.external,
            priority=self.priority,
            first=first_agent(self.priority, active),  # the first model context: the agent acting first
        )
        self.engine.start_rows([self.row], spec, [seed])
        self.ordered_in_slots = self.engine.cfg.variant is Variant.TRAJEGLISH and not externals_first
        self.n, self.T = scenario.num_agents, cur + 1 + int(horizon)
        self._t = cur

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

    def _pending(self) -> np.ndarray:
        t = self.t
        if t >= self.T - 1:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.external & ~self.engine.known[self.row, : self.n, t] & self.valid[:, t])

    def external_order(self) -> np.ndarray:
        """External agents still to act this step, in the order they will be asked for."""
        pending = self._pending()
        by_priority = pending[np.argsort(self.priority[pending], kind="stable")]
        plan = self.engine.plan[self.row]
        if not self.ordered_in_slots or plan is None:
            return by_priority
        planned = plan.acting_order[np.isin(plan.acting_order, pending)]
        return np.concatenate([planned, by_priority[~np.isin(by_priority, planned)]]).astype(np.int64)

    def advance(self) -> int | None:
        """The next external agent to supply, or None when the step is complete (NPCs decoded)."""
        if self.shared and self.t != self._t:  # the owner has stepped the engine: this step is complete
            self._t = self.t
            return None
        if self.externals_first:
            pending = self._pending()
            if len(pending):
                return int(pending[np.argmin(self.priority[pending])])
        if self.shared:
            raise RuntimeError(
                "this scene's NPCs are decoded by the batched environment that owns the engine "
                "(call engine.step() once every scene has supplied its external agents)"
            )
        waiting = self.engine.advance()
        self._t = self.t
        return None if waiting is None else int(waiting[1][0])

    def supply(self, agent: int, next_xyh: np.ndarray, valid: bool = True) -> None:
        """Set an external agent's next state; the model sees it tokenized."""
        self.engine.supply([self.row], [agent], np.asarray(next_xyh, dtype=np.float64)[None], [valid])
