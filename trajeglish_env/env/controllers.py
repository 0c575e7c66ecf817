"""Rule-based controllers for external agents: a rule-based NPC policy's next state for the agent, turned
into the env's action type (used by ``trajeglish demo`` and by ``policies.IDMPolicy`` and friends)."""

from __future__ import annotations

from typing import Any

import numpy as np

from trajeglish_env.env.npc import IDMNPC, make_npc_policy


class RuleBasedController:
    """Drives external agents with ``replay``, ``constant_velocity`` or ``idm`` (each agent on its own;
    the IDM's path position and speed are re-synchronised with the agent's actual state every step)."""

    def __init__(self, name: str):
        make_npc_policy(name)  # validates the name
        self.name = name
        self._scenario: Any = None
        self._policy: Any = None
        self._sim: Any = None

    def reset(self) -> None:
        """Forget the last episode: the next :meth:`action` starts from the new episode's state (a scene
        played again is the same object, so the scene alone cannot tell episodes apart)."""
        self._scenario = self._policy = self._sim = None

    def action(self, env: Any, agent: str) -> Any:
        """The action of external ``agent`` (``env``: the AEC env, wrapped or not) at its turn."""
        raw = env.unwrapped
        sim = raw.sim
        if self._scenario is not raw.scenario or self._sim is not sim:
            self._policy = make_npc_policy(self.name)
            self._policy.reset(raw.scenario, sim.external.copy(), raw.scenario.current_index, 0)
            self._scenario, self._sim = raw.scenario, sim
            if isinstance(self._policy, IDMNPC):
                self._follow_long_routes(self._policy, sim)
        i = raw.agent_index(agent)
        rows = np.array([i])
        if isinstance(self._policy, IDMNPC):
            here = sim.driver.xyh[i, sim.t, :2][None]
            s, _, _ = self._policy.paths.project(rows, here, self._policy.s[rows])
            self._policy.s[i], self._policy.v[i] = s[0], float(sim.kin.speed[i])
        target, ok = self._policy.act(sim.view(), rows)
        if not ok[0]:  # e.g. the log has ended: keep going at constant velocity
            target = sim.driver.xyh[i, sim.t][None].copy()
            target[0, :2] += sim.driver.xyh[i, sim.t, :2] - sim.driver.xyh[i, max(sim.t - 1, 0), :2]
        return raw.action_towards(agent, target[0])

    @staticmethod
    def _follow_long_routes(policy: IDMNPC, sim: Any) -> None:
        """In an episode past the log, IDM drives each external agent along its env route (the logged path
        continued along the lanes) instead of its logged path, and stops smoothly where the route ends."""
        ext = sim.external_index
        longer = sim.routes.length > policy.paths.length[ext]
        if longer.any():
            policy.paths = policy.paths.with_rows(ext[longer], sim.routes, np.flatnonzero(longer))
            policy.stops_at_end[ext[longer]] = True
