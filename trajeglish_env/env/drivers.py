"""Step drivers: walk one timestep's intra-timestep order, letting the NPCs act and pausing at every
external agent whose next state is needed (the engine's ``advance`` / ``supply`` protocol).

:class:`EngineDriver` runs the Trajeglish model (one token per NPC through the KV cache, any scene size);
:class:`OrderedDriver` runs a rule-based :class:`~trajeglish_env.env.npc.NPCPolicy` group by group. Both
expose the exact states ``xyh [N,T,3]`` / ``valid [N,T]`` (T = current + 1 + horizon), the step ``t``
and who has ``moved`` in it.
"""

from __future__ import annotations

from dataclasses import replace
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
    """Trajeglish NPCs through :class:`~trajeglish_env.sampler.RolloutEngine` (one rollout).

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
        temperature: float = 1.0,
        top_p: float = 1.0,
        externals_first: bool = False,
    ):
        from trajeglish_env.model.config import Variant
        from trajeglish_env.sampler.engine import RolloutEngine, SamplingConfig

        cur = scenario.current_index
        self.scenario = scenario
        self.external = np.asarray(external, dtype=bool)
        self.priority = np.asarray(priority, dtype=np.float64)
        self.externals_first = externals_first
        active = scenario.valid[:, cur]
        # the first model context is centred on the agent acting first (the engine centres it on the sdc)
        centred = replace(scenario, sdc=first_agent(self.priority, active))
        controlled = active & ~self.external
        self.engine = RolloutEngine(
            ckpt,  # type: ignore[arg-type]
            centred,
            1,
            int(horizon),
            controlled,
            self.external,
            priority=self.priority,
            config=SamplingConfig(temperature=temperature, top_p=top_p, seed=int(seed)),
        )
        self.ordered_in_slots = self.engine.cfg.variant is Variant.TRAJEGLISH and not externals_first
        self.xyh = self.engine.xyh[0]
        self.valid = self.engine.valid[0]

    @property
    def t(self) -> int:
        """The current step of the engine."""
        return self.engine.t

    def moved(self) -> np.ndarray:
        """``[N]`` agents whose token of this step is decided (log-replayed agents: always)."""
        t = self.engine.t
        if t >= self.engine.T - 1:  # the episode is over: nobody moves any more
            return np.zeros(self.engine.N, dtype=bool)
        return self.engine.known[0, :, t] & self.valid[:, t]

    def _pending(self) -> np.ndarray:
        t = self.engine.t
        if t >= self.engine.T - 1:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.external & ~self.engine.known[0, :, t] & self.valid[:, t])

    def external_order(self) -> np.ndarray:
        """External agents still to act this step, in the order they will be asked for."""
        pending = self._pending()
        by_priority = pending[np.argsort(self.priority[pending], kind="stable")]
        if not self.ordered_in_slots or not self.engine.plan:
            return by_priority
        acting = self.engine.plan[0].acting_order
        planned = acting[np.isin(acting, pending)]
        return np.concatenate([planned, by_priority[~np.isin(by_priority, planned)]]).astype(np.int64)

    def advance(self) -> int | None:
        """The next external agent to supply, or None when the step is complete (NPCs decoded)."""
        if self.externals_first:
            pending = self._pending()
            if len(pending):
                return int(pending[np.argmin(self.priority[pending])])
        return self.engine.advance()

    def supply(self, agent: int, next_xyh: np.ndarray, valid: bool = True) -> None:
        """Set an external agent's next state; the model sees it tokenized."""
        self.engine.supply(agent, np.asarray(next_xyh, dtype=np.float64), valid=valid)
