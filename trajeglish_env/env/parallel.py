"""The parallel API, derived from the AEC env with PettingZoo's ``aec_to_parallel`` wrapper.

Meaning: every external agent's action is chosen from the observations taken when the first external
agent of the step is to act (NPCs ordered before it have moved, the others not), and the actions are
applied in the intra-timestep order, NPCs acting in between exactly as in the AEC env.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import aec_to_parallel_wrapper

from trajeglish_env.env.actions import check_action
from trajeglish_env.env.aec import env
from trajeglish_env.env.config import EnvConfig


class SceneAwareParallelEnv(aec_to_parallel_wrapper):
    """``aec_to_parallel_wrapper`` that refreshes ``possible_agents`` at every reset (with track names
    each scene has its own agents; the stock wrapper copies them once, at construction) and checks a step's
    actions (one per live agent, no unknown agent, each inside its space; a finished agent's, or one of
    ``possible_agents`` absent from the episode, is ignored) before any agent acts."""

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Every live agent's action at once (see the module docstring); refused before ``reset``, for a
        missing or unknown agent, or for an action outside its space, before anything moves. The stock
        wrapper's loop, less its ``last()`` per agent (an observation built and dropped), with the step's
        observations built in one pass."""
        aec = self.aec_env
        raw = aec.unwrapped
        raw._sim()  # "call reset() before using the environment"
        if not isinstance(actions, dict):
            raise TypeError(
                f"step: expected a dict agent name -> action, got {type(actions).__name__}; the agents are "
                f"{aec.agents}"
            )
        missing = [a for a in aec.agents if a not in actions]
        # actions for agents of the episode that have finished are ignored, as PettingZoo's own wrapper does
        unknown = sorted(map(str, set(actions) - set(aec.agents) - set(aec.possible_agents)))
        if missing:
            also = (
                f"; actions were given for {unknown}, which are no agents of the episode" if unknown else ""
            )
            raise KeyError(f"step: no action for agent(s) {missing}{also}")
        if unknown:
            raise KeyError(f"step: no live agent(s) {unknown}; the agents are {aec.agents}")
        for agent in aec.agents:
            check_action(aec.action_space(agent), actions[agent], agent)
        rewards: dict[str, float] = defaultdict(float)
        for agent in aec.agents:
            if agent != aec.agent_selection:  # the AEC env finishes agents only at a step's end
                raise AssertionError(f"expected agent {agent} to act, got {aec.agent_selection}")
            aec.step(actions[agent])
            for other in aec.agents:
                rewards[other] += aec.rewards[other]
        terminations, truncations, infos = dict(aec.terminations), dict(aec.truncations), dict(aec.infos)
        observations = raw.observe_all(aec.agents)
        while aec.agents and (aec.terminations[aec.agent_selection] or aec.truncations[aec.agent_selection]):
            aec.step(None)
        self.agents = aec.agents
        return observations, rewards, terminations, truncations, infos

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        out = super().reset(seed=seed, options=options)
        self.possible_agents = list(self.aec_env.possible_agents)
        return out


def parallel_env(
    scenes: Any = None, config: EnvConfig | None = None, render_mode: str | None = None, **options: Any
) -> ParallelEnv:
    """The parallel environment (same arguments as :class:`~trajeglish_env.env.aec.raw_env`)."""
    # the order-enforced AEC env, as PettingZoo's own pairs wrap it: parallel_to_aec gives that env back
    return SceneAwareParallelEnv(env(scenes, config, render_mode, **options))
