"""The Policy protocol for external agents, and the simple policies: random, replay, constant velocity.

A policy is asked for one agent's action at that agent's turn in the AEC loop::

    class MyPolicy:
        def reset(self, env, agent: str) -> None: ...          # a new episode (optional state)
        def act(self, env, agent: str, observation) -> action: ...

``env`` is the (wrapped) AEC env, or an ``EgoEnv`` (``Ego-v0``; ``agent``: its ``env.agent``); rule-based
policies read the simulation through ``env.unwrapped`` (``scenario``, ``sim.view()``, ``agent_index(agent)``,
``action_towards(agent, target_state)``).
"""

from __future__ import annotations

import copy
import zlib
from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Policy(Protocol):
    """Chooses actions for external agents (see the module docstring)."""

    def reset(self, env: Any, agent: str) -> None: ...

    def act(self, env: Any, agent: str, observation: Any) -> Any: ...


def current_state(env: Any, agent: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """(state now [3], state one step earlier [3], whether that earlier state exists) of an external agent."""
    raw = env.unwrapped
    i, t = raw.agent_index(agent), raw.sim.t
    xyh, valid = raw.sim.driver.xyh, raw.sim.driver.valid
    return xyh[i, t], xyh[i, max(t - 1, 0)], bool(valid[i, max(t - 1, 0)] and t > 0)


def constant_velocity_target(env: Any, agent: str) -> np.ndarray:
    """The state one step ahead at the agent's last velocity and heading."""
    now, before, ok = current_state(env, agent)
    target = now.copy()
    if ok:
        target[:2] += now[:2] - before[:2]
    return target


class RandomPolicy:
    """Uniformly random actions (each agent's own seeded copy of its action space)."""

    def __init__(self, seed: int = 0):
        self.seed = seed
        self._spaces: dict[str, Any] = {}

    def reset(self, env: Any, agent: str) -> None:
        """Prepare for a new episode of ``agent``: its draws follow this policy's seed, the agent's name and
        the episode's seed (the same episode whatever the object played before)."""
        space = env.action_space(agent) if callable(env.action_space) else env.action_space  # an EgoEnv's
        space = copy.deepcopy(space)
        episode = int(getattr(env.unwrapped.sim, "seed", 0))
        seq = np.random.SeedSequence([self.seed, zlib.crc32(agent.encode()), episode])
        space.seed(int(seq.generate_state(1)[0]))
        self._spaces[agent] = space

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The action of ``agent`` at its turn."""
        if agent not in self._spaces:
            self.reset(env, agent)
        return self._spaces[agent].sample()


class FunctionPolicy:
    """A function ``observation -> action`` as a policy (stateless: the same function for every agent)."""

    def __init__(self, function: Any):
        if not callable(function):
            raise TypeError(f"FunctionPolicy: expected a function observation -> action, got {function!r}")
        self.function = function

    def reset(self, env: Any, agent: str) -> None:
        """Nothing to prepare: the function keeps no state of ours."""
        return None

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The function's action for ``observation``."""
        return self.function(observation)


class ConstantVelocityPolicy:
    """Keeps the agent's velocity and heading (the action that best does, for any action type)."""

    def reset(self, env: Any, agent: str) -> None:
        """Prepare for a new episode of ``agent``."""
        return None

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The action of ``agent`` at its turn."""
        return env.unwrapped.action_towards(agent, constant_velocity_target(env, agent))


class ReplayPolicy:
    """Follows the agent's logged trajectory (constant velocity where the log has ended)."""

    def reset(self, env: Any, agent: str) -> None:
        """Prepare for a new episode of ``agent``."""
        return None

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The action of ``agent`` at its turn."""
        raw = env.unwrapped
        i, t1 = raw.agent_index(agent), raw.sim.t + 1
        sc = raw.scenario
        if t1 < sc.num_steps and sc.valid[i, t1]:
            target = sc.xyh[i, t1]
        else:
            target = constant_velocity_target(env, agent)
        return raw.action_towards(agent, target)
