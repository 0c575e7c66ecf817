"""The PettingZoo AEC environment: external agents act one at a time in intra-timestep order, and the NPCs
between them act in between (Trajeglish: one model token each through the KV cache)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv
from pettingzoo.utils import wrappers

from trajeglish_env.env.actions import check_action, make_action_space, named_action_space
from trajeglish_env.env.config import EnvConfig
from trajeglish_env.env.episodes import EpisodeStream
from trajeglish_env.env.observations import observation_space
from trajeglish_env.env.scene_batch import SceneBatch
from trajeglish_env.env.scenes import scene_set
from trajeglish_env.env.simulation import AgentReport, Simulation, agent_names, select_external
from trajeglish_env.heap import release_freed_memory
from trajeglish_env.scenario import Scenario, agent_name


class raw_env(AECEnv):  # noqa: N801 (PettingZoo naming convention)
    """Driving scenes with Trajeglish (or rule-based) NPCs; the external agents are the AEC agents.

    Agents: the external agents of the current scene, named ``<kind>_<track id>`` (e.g. ``vehicle_2406``),
    or ``agent_0`` .. by slot (``agent_names="slot"``: fixed ``possible_agents``); ``agents`` is kept in
    this step's acting order. ``scenes``: None (the shipped bundle), Scenarios, a path to scenario files,
    or ``"highway[:kinds]"``; ``reset(seed, options={"scene": index or scenario_id})``. Settings:
    :class:`~trajeglish_env.env.config.EnvConfig` (or its fields as keywords).

    Observation (same space for every agent): ``vector`` Box[-1,1]^D float32 or ``bev`` Box uint8
    [5,H,W], see :mod:`trajeglish_env.env.observations`. Action: ``continuous`` Box[-1,1]^2 (acceleration,
    steering), ``delta`` Box (dx, dy, dh) or ``token`` Discrete(V), see :mod:`trajeglish_env.env.actions`.
    Rewards, terminations (collision, off-road, end of route) and truncation (``max_cycles``) are computed
    at the end of every timestep; ``infos[agent]`` holds ``collision``, ``offroad``, ``goal`` (this
    step), ``has_goal``, ``progress_m``, ``route_fraction``, ``collision_steps``, ``offroad_steps`` and
    ``goal_reached``
    (so far). A finished agent leaves the scene at the next step.
    """

    metadata = {
        "name": "trajeglish_v0",
        "render_modes": ["human", "rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        **options: Any,
    ):
        super().__init__()
        self.config = (config or EnvConfig()).with_overrides(**options)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}"
            )
        self.render_mode = render_mode
        self.scenes = scene_set(scenes)
        self.batch = SceneBatch(1, self.config, self.config.torch_threads)
        self.checkpoint, self.vocabulary = self.batch.checkpoint, self.batch.vocabulary
        self._observation_space = observation_space(self.config.observation, self.config.obs)
        vocab_size = self.vocabulary.size if self.vocabulary is not None else 1
        self._action_template = make_action_space(self.config.action, vocab_size)
        self._action_spaces: dict[str, spaces.Space] = {}
        self._episodes = EpisodeStream(self.scenes)
        self.np_random = self._episodes.np_random
        self.possible_agents = self._first_scene_agents()
        if self.config.slot_names is not None:  # a fixed-size global state needs fixed agents
            self.state_space = stacked_space(self._observation_space, len(self.possible_agents))
        self.agents = []
        self.sim: Simulation | None = None
        self._renderer: Any = None  # a LiveRenderer, made on the first render (imports matplotlib)

    def _first_scene_agents(self) -> list[str]:
        """``possible_agents`` before the first reset: the slot names (``agent_names="slot"``: for the env's
        life), or the first scene's external agents, or none when the external spec does not fit that scene
        (track ids of another scene: checked at reset, against the scene the episode plays)."""
        if (slots := self.config.slot_names) is not None:
            return slots
        first = self.scenes.get(0)
        try:
            external = select_external(first, self.config.external, np.random.default_rng(0))
        except ValueError:
            return []
        names = agent_names(first)
        return [names[i] for i in external]

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Space:
        """The observation space (the same object for every agent)."""
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Space:
        """The agent's own action space object (its sampling seeded from the agent's name)."""
        if agent not in self._action_spaces:
            n = getattr(self._action_template, "n", 1)
            self._action_spaces[agent] = named_action_space(self.config.action, n, agent)
        return self._action_spaces[agent]

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        """Start an episode on the scene ``options["scene"]`` (index or scenario_id) or one drawn from
        the seed; the NPCs acting before the first external agent act now."""
        self.scenario, rng = self._episodes.next(seed, options)
        self.np_random = self._episodes.np_random
        self._start(self.scenario, rng)
        if self.render_mode == "human":  # Gymnasium's human mode shows the reset state too
            self.render()

    def _start(self, scenario: Scenario, rng: np.random.Generator) -> None:
        self.sim = sim = self.batch.start(0, scenario, rng)
        names = [sim.names[i] for i in sim.external_index]
        if self.config.slot_names is None:  # track names: each scene has its own (slot names are fixed)
            self.possible_agents = names
        self._index = {name: int(i) for name, i in zip(names, sim.external_index, strict=True)}
        self.rewards = dict.fromkeys(names, 0.0)
        self._cumulative_rewards = dict.fromkeys(names, 0.0)
        self.terminations = dict.fromkeys(names, False)
        self.truncations = dict.fromkeys(names, False)
        self.infos: dict[str, dict[str, Any]] = {sim.names[i]: sim.agent_info(i) for i in sim.external_index}
        first = self.batch.advance()
        if first is None:  # no external agent acts (cannot happen: they are present at the current step)
            raise RuntimeError(f"scenario {scenario.scenario_id!r}: no external agent to act")
        self.agents = [sim.names[i] for i in sim.external_order()]
        self.agent_selection = sim.names[int(first[1][0])]

    def observe(self, agent: str) -> np.ndarray:
        """The agent's observation now (showing the moves made so far in this step)."""
        self._sim()
        return self.batch.observe([0], [self.agent_index(agent)])[0]

    def observe_all(self, agents: list[str]) -> dict[str, np.ndarray]:
        """The observations of ``agents`` now, in one geometry pass (each equal to :meth:`observe`'s)."""
        self._sim()
        if not agents:
            return {}
        values = self.batch.observe([0] * len(agents), [self.agent_index(a) for a in agents])
        return dict(zip(agents, values, strict=True))

    def step(self, action: Any) -> None:
        """Apply the selected agent's action, let the NPCs up to the next external agent act; at the end
        of a timestep compute rewards, terminations and truncations."""
        agent = self.agent_selection
        if self.terminations[agent] or self.truncations[agent]:
            self._was_dead_step(action)
            return
        value = check_action(self.action_space(agent), action, agent)
        self._cumulative_rewards[agent] = 0.0
        self.batch.supply([0], [self._index[agent]], [value])
        nxt = self.batch.advance()
        if nxt is not None:
            self._clear_rewards()
            self.agent_selection = self._sim().names[int(nxt[1][0])]
            self._accumulate_rewards()
            return
        self._end_of_timestep(self.batch.finish([0])[0])
        self._accumulate_rewards()
        if self.render_mode == "human":  # one window update per timestep, not per external agent's action
            self.render()

    def _end_of_timestep(self, reports: dict[str, AgentReport]) -> None:
        sim = self._sim()
        self._clear_rewards()
        for name, report in reports.items():
            self.rewards[name] = report.reward
            self.terminations[name] = report.terminated
            self.truncations[name] = report.truncated
            self.infos[name] = report.info
        done_names = [name for name in reports if sim.retired[self._index[name]]]
        nxt = self.batch.advance() if sim.has_live_agents else None
        if nxt is not None:
            self.agents = [sim.names[i] for i in sim.external_order()] + done_names
            self.agent_selection = sim.names[int(nxt[1][0])]
        else:
            self.agents = done_names
            self.agent_selection = done_names[0]
        self._deads_step_first()

    def _clear_rewards(self) -> None:
        """Zero the per-step rewards (as Python floats, like every reward this env reports)."""
        for agent in self.rewards:
            self.rewards[agent] = 0.0

    def _sim(self) -> Simulation:
        if self.sim is None:
            raise RuntimeError("call reset() before using the environment")
        return self.sim

    def state(self) -> np.ndarray:
        """With slot names (``agent_names="slot"``): every slot's observation now, stacked along the first
        axis (zeros for a slot the episode leaves empty or whose agent has left): a fixed-size global view
        for centralised critics (``state_space``). With track names the agents, and so any such size,
        change with the scene: NotImplementedError (``env.unwrapped.sim`` holds the whole scene)."""
        slots = self.config.slot_names
        if slots is None:
            raise NotImplementedError(
                "state(): a fixed-size global state needs fixed agents: pass agent_names='slot' (with track "
                "names env.unwrapped.sim holds the whole scene)"
            )
        self._sim()
        space = self._observation_space
        parts = np.zeros((len(slots), *space.shape), space.dtype)
        for agent, obs in self.observe_all(list(self.agents)).items():
            parts[slots.index(agent)] = obs
        return parts.reshape(-1, *space.shape[1:])

    # ------------------------------------------------------------------ helpers for policies and users
    def agent_index(self, agent: str) -> int:
        """Index in the scene of an external agent's name."""
        if agent not in self._index:
            raise KeyError(f"no external agent named {agent!r}; external agents: {sorted(self._index)}")
        return self._index[agent]

    def agent_track(self, agent: str) -> str:
        """The class and track id of an external agent (``vehicle_68``; its name too unless the agents
        are named by slot, ``agent_names="slot"``)."""
        i = self.agent_index(agent)
        return agent_name(self.scenario.kind[i], self.scenario.track_id[i])

    def action_towards(self, agent: str, target: np.ndarray) -> np.ndarray | int:
        """The action that brings external ``agent`` closest to state ``target [3]`` at the next step."""
        return self._sim().action_towards(self.agent_index(agent), target)

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """The current step as an RGB array (``rgb_array``) or in a window (``human``)."""
        if self.render_mode is None:
            import gymnasium

            gymnasium.logger.warn(
                "render() called without a render_mode; pass render_mode='rgb_array' or 'human'"
            )
            return None
        renderer = self._live_renderer().of(self._sim())
        frame = renderer.frame(self._sim().t)
        if self.render_mode == "rgb_array":
            return frame
        renderer.show(frame)
        return None

    def save_video(self, path: str | os.PathLike[str], fps: int | None = None) -> Path:
        """Write the episode so far (from the current index to now) as a GIF or MP4."""
        sim = self._sim()
        return (
            self._live_renderer().of(sim).save(path, range(self.scenario.current_index, sim.t + 1), fps or 10)
        )

    def _live_renderer(self) -> Any:
        if self._renderer is None:
            from trajeglish_env.render import LiveRenderer

            self._renderer = LiveRenderer(
                self.config.render_size, self.config.render_radius, self.config.render_legend
            )
        return self._renderer

    def close(self) -> None:
        """Release the renderer and its window, and the C heap's free pages (:mod:`trajeglish_env.heap`)."""
        if self._renderer is not None:
            self._renderer.close()
        release_freed_memory()


def stacked_space(space: spaces.Box, n: int) -> spaces.Box:
    """``n`` copies of an observation space stacked along its first axis (the slots' global state)."""
    return spaces.Box(
        np.concatenate([space.low] * n, axis=0), np.concatenate([space.high] * n, axis=0), dtype=space.dtype
    )


def env(
    scenes: Any = None, config: EnvConfig | None = None, render_mode: str | None = None, **options: Any
) -> AECEnv:
    """The AEC env in PettingZoo's order-enforcing wrapper (actions are checked by the env itself)."""
    return wrappers.OrderEnforcingWrapper(raw_env(scenes, config, render_mode, **options))
