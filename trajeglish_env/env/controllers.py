"""Rule-based controllers for external agents: a rule-based NPC policy's next state for the agent, turned
into the env's action type (used by ``trajeglish demo`` and by ``policies.IDMPolicy`` and friends)."""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from trajeglish_env.env.actions import class_limits
from trajeglish_env.env.npc import IDMNPC, make_npc_policy


class RuleBasedController:
    """Drives external agents with ``replay``, ``constant_velocity`` or ``idm`` (each agent on its own;
    the IDM's path position and speed are re-synchronised with the agent's actual state every step). One
    controller may drive several envs at once: it keeps the rule's state per episode (simulation), and
    pickles without them."""

    def __init__(self, name: str):
        make_npc_policy(name)  # validates the name
        self.name = name
        self._states: weakref.WeakKeyDictionary[Any, tuple[Any, Any]] = weakref.WeakKeyDictionary()

    def reset(self) -> None:
        """Forget the episodes so far: the next :meth:`action` starts from its episode's state (a scene
        played again is the same object, so the scene alone cannot tell episodes apart)."""
        self._states = weakref.WeakKeyDictionary()

    def __getstate__(self) -> dict[str, Any]:
        return {"name": self.name}  # the episodes' states stay with their envs

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["name"])  # type: ignore[misc]

    def action(self, env: Any, agent: str) -> Any:
        """The action of external ``agent`` (``env``: the AEC env, wrapped or not) at its turn."""
        raw = env.unwrapped
        sim = raw.sim
        scenario, policy = self._states.get(sim, (None, None))
        if scenario is not raw.scenario:
            policy = make_npc_policy(self.name)
            policy.reset(raw.scenario, sim.external.copy(), raw.scenario.current_index, 0)
            self._states[sim] = (raw.scenario, policy)
            if isinstance(policy, IDMNPC):
                self._follow_long_routes(policy, sim)
        return self._act(raw, sim, policy, agent)

    def _act(self, raw: Any, sim: Any, policy: Any, agent: str) -> Any:
        """The action of ``agent`` under its episode's ``policy``."""
        i = raw.agent_index(agent)
        rows = np.array([i])
        speed = float(sim.kin.speed[i])
        if isinstance(policy, IDMNPC):
            here = sim.driver.xyh[i, sim.t, :2][None]
            s, _, _ = policy.paths.project(rows, here, policy.s[rows])
            policy.s[i], policy.v[i] = s[0], speed
        target, ok = policy.act(sim.view(), rows)
        if not ok[0]:  # e.g. the log has ended: keep going at constant velocity
            target = sim.driver.xyh[i, sim.t][None].copy()
            target[0, :2] += sim.driver.xyh[i, sim.t, :2] - sim.driver.xyh[i, max(sim.t - 1, 0), :2]
        action = raw.action_towards(agent, target[0])
        if isinstance(policy, IDMNPC) and ok[0] and sim.config.action == "continuous":
            # IDM's own acceleration: the target's distance ahead reads 0 where a car at rest stands beside
            # a curving path with the next centimetre behind its nose, and it stayed at rest for good
            limits = class_limits(int(raw.scenario.kind[i]), sim.config.limits)
            accel = (float(policy.v[i]) - speed) / sim.dt
            scale = limits.max_accel if accel >= 0 else limits.max_brake
            action[0] = np.float32(np.clip(accel / scale, -1.0, 1.0))  # type: ignore[index]
        return action

    @staticmethod
    def _follow_long_routes(policy: IDMNPC, sim: Any) -> None:
        """In an episode past the log, IDM drives each external agent along its env route (the logged path
        continued along the lanes) instead of its logged path, and stops smoothly where the route ends."""
        ext = sim.external_index
        longer = sim.routes.length > policy.paths.length[ext]
        if longer.any():
            policy.paths = policy.paths.with_rows(ext[longer], sim.routes, np.flatnonzero(longer))
            policy.stops_at_end[ext[longer]] = True
