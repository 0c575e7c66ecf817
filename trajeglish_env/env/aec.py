"""The PettingZoo AEC environment: external agents act one at a time in intra-timestep order, and the NPCs
between them act in between (Trajeglish: one model token each through the KV cache)."""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import AECEnv
from pettingzoo.utils import wrappers

from trajeglish_env.env.actions import action_towards, check_action, make_action_space
from trajeglish_env.env.config import EnvConfig, TrajeglishNPC
from trajeglish_env.env.npc import NPCPolicy, make_npc_policy
from trajeglish_env.env.observations import observation_space
from trajeglish_env.env.scenes import scene_index, scene_set
from trajeglish_env.env.simulation import Simulation, agent_names, select_external
from trajeglish_env.scenario import Scenario


class raw_env(AECEnv):  # noqa: N801 (PettingZoo naming convention)
    """Driving scenes with Trajeglish (or rule-based) NPCs; the external agents are the AEC agents.

    Agents: the external agents of the current scene, named ``<kind>_<track id>`` (e.g. ``vehicle_2406``);
    ``agents`` is kept in this step's acting order. ``scenes``: None (the shipped bundle), Scenarios, a
    path to scenario files, or ``"highway[:kinds]"``; ``reset(seed, options={"scene": index or
    scenario_id})``. Settings: :class:`~trajeglish_env.env.config.EnvConfig` (or its fields as keywords).

    Observation (same space for every agent): ``vector`` Box[-1,1]^D float32 or ``bev`` Box uint8
    [5,H,W], see :mod:`trajeglish_env.env.observations`. Action: ``continuous`` Box[-1,1]^2 (acceleration,
    steering), ``delta`` Box (dx, dy, dh) or ``token`` Discrete(V), see :mod:`trajeglish_env.env.actions`.
    Rewards, terminations (collision, off-road, end of route) and truncation (``max_cycles``) are computed
    at the end of every timestep; ``infos[agent]`` holds ``collision``, ``offroad``, ``goal`` (this
    step), ``progress_m``, ``route_fraction``, ``collision_steps`` and ``offroad_steps`` (so far). A
    finished agent leaves the scene at the next step.
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
        self._npc, self._sampling, self.checkpoint = _resolve_npc(self.config.npc)
        self.vocabulary = self.checkpoint.vocabulary if self.checkpoint is not None else None
        if self.config.action == "token" and self.vocabulary is None:
            from trajeglish_env.tokenizer.vocabulary import load_default_tokenizer

            self.vocabulary = load_default_tokenizer()
        if self.checkpoint is not None and self.config.torch_threads is not None:
            import torch

            torch.set_num_threads(self.config.torch_threads)
        self._observation_space = observation_space(self.config.observation, self.config.obs)
        vocab_size = self.vocabulary.size if self.vocabulary is not None else 1
        self._action_template = make_action_space(self.config.action, vocab_size)
        self._action_spaces: dict[str, spaces.Space] = {}
        self.np_random, _ = seeding.np_random(None)
        first = self.scenes.get(0)
        names = agent_names(first)
        self.possible_agents = [
            names[i] for i in select_external(first, self.config.external, np.random.default_rng(0))
        ]
        self.agents = []
        self.sim: Simulation | None = None
        self._shared_row: tuple[Any, int] | None = None  # set by a batched env that owns the engine
        self._suspended = False
        self._renderer: Any = None  # an EpisodeRenderer, made on the first render (imports matplotlib)

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Space:
        """The observation space (the same object for every agent)."""
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Space:
        """The agent's own action space object (its sampling seeded from the agent's name)."""
        if agent not in self._action_spaces:
            space = make_action_space(self.config.action, getattr(self._action_template, "n", 1))
            space.seed(zlib.crc32(agent.encode()))
            self._action_spaces[agent] = space
        return self._action_spaces[agent]

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        """Start an episode on the scene ``options["scene"]`` (index or scenario_id) or one drawn from
        the seed; the NPCs acting before the first external agent act now."""
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        index = scene_index((options or {}).get("scene"), self.scenes)  # the only option read
        if index is None:
            index = int(self.np_random.integers(len(self.scenes)))
        self.scenario = self.scenes.get(index)
        self._suspended = False
        self._start(self.scenario)

    def _start(self, scenario: Scenario) -> None:
        rng = np.random.default_rng(int(self.np_random.integers(2**63 - 1)))
        npc = make_npc_policy(self._npc) if isinstance(self._npc, str) else self._npc
        self.sim = sim = Simulation(
            scenario, self.config, npc, self.vocabulary, rng, self._sampling, self._shared_row
        )
        self.possible_agents = [sim.names[i] for i in sim.external_index]
        self._index = {sim.names[i]: int(i) for i in sim.external_index}
        self.rewards = dict.fromkeys(self.possible_agents, 0.0)
        self._cumulative_rewards = dict.fromkeys(self.possible_agents, 0.0)
        self.terminations = dict.fromkeys(self.possible_agents, False)
        self.truncations = dict.fromkeys(self.possible_agents, False)
        self.infos: dict[str, dict[str, Any]] = {a: {} for a in self.possible_agents}
        first = sim.advance()
        if first is None:  # no external agent acts (cannot happen: they are present at the current step)
            raise RuntimeError(f"scenario {scenario.scenario_id!r}: no external agent to act")
        self.agents = [sim.names[i] for i in sim.external_order()]
        self.agent_selection = sim.names[first]
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def observe(self, agent: str) -> np.ndarray:
        """The agent's observation now (showing the moves made so far in this step)."""
        return self._sim().observe(self.agent_index(agent))

    def step(self, action: Any) -> None:
        """Apply the selected agent's action, let the NPCs up to the next external agent act; at the end
        of a timestep compute rewards, terminations and truncations."""
        prepared = self.prepare_action(action)
        if prepared is None:
            return
        sim, index, value = prepared
        sim.apply(index, value)
        self.after_action()

    def prepare_action(self, action: Any) -> tuple[Simulation, int, Any] | None:
        """First part of :meth:`step`: a finished agent's step (returns None), else the selected agent's
        validated action, with its simulation and index, to apply (a batched env applies them together)."""
        agent = self.agent_selection
        if self.terminations[agent] or self.truncations[agent]:
            self._was_dead_step(action)
            return None
        value = check_action(self.action_space(agent), action, agent)
        self._cumulative_rewards[agent] = 0.0
        return self._sim(), self._index[agent], value

    def after_action(self) -> None:
        """Last part of :meth:`step`, once the action is applied."""
        if self._sim().ready_for_batch():  # a batched env decodes every scene's NPCs at once, then resumes us
            self._suspended = True
            return
        self._finish_action()

    @property
    def suspended(self) -> bool:
        """The step waits for the batched env that owns the NPC engine (see :meth:`resume`)."""
        return self._suspended

    def resume(self) -> None:
        """Finish the step after the owner of the shared engine has decoded this step's NPCs."""
        if not self._suspended:
            raise RuntimeError("resume(): the env is not waiting for a batched NPC step")
        self._suspended = False
        self._finish_action()

    def _finish_action(self) -> None:
        """After an external agent's action: let the NPCs up to the next external agent act, or end the
        timestep."""
        sim = self._sim()
        nxt = sim.advance()
        if nxt is not None:
            self._clear_rewards()
            self.agent_selection = sim.names[nxt]
        else:
            self._end_of_timestep()
        self._accumulate_rewards()
        if self.render_mode == "human":
            self.render()

    def _end_of_timestep(self) -> None:
        sim = self._sim()
        live, out = sim.finish_step()
        self._clear_rewards()
        truncated = sim.horizon_reached
        r = self.config.reward
        for k, a in enumerate(live):
            name = sim.names[a]
            row = sim.route_row[int(a)]
            self.rewards[name] = float(out.reward[k])
            done = bool(
                (r.terminate_on_collision and out.collision[k])
                or (r.terminate_on_offroad and out.offroad[k])
                or (r.terminate_on_goal and out.goal[k])
            )
            self.terminations[name] = done
            self.truncations[name] = bool(truncated and not done)
            self.infos[name] = {
                "collision": bool(out.collision[k]),
                "offroad": bool(out.offroad[k]),
                "goal": bool(out.goal[k]),
                "progress_m": float(sim.progress[row]),
                "route_fraction": float(sim.progress[row] / max(sim.routes.length[row], 1e-6)),
                "collision_steps": int(sim.collision_steps[row]),
                "offroad_steps": int(sim.offroad_steps[row]),
            }
            if done or truncated:
                sim.retire(int(a))
        live_names = [sim.names[a] for a in live if not sim.retired[a]]
        done_names = [sim.names[a] for a in live if sim.retired[a]]
        if live_names:
            first = sim.advance()
            assert first is not None
            order = [sim.names[i] for i in sim.external_order()]
            self.agents = order + done_names
            self.agent_selection = sim.names[first]
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

    # ------------------------------------------------------------------ helpers for policies and users
    def agent_index(self, agent: str) -> int:
        """Index in the scene of an external agent's name."""
        if agent not in self._index:
            raise KeyError(f"no external agent named {agent!r}; external agents: {sorted(self._index)}")
        return self._index[agent]

    def action_towards(self, agent: str, target: np.ndarray) -> np.ndarray | int:
        """The action that brings external ``agent`` closest to state ``target [3]`` at the next step."""
        sim, i = self._sim(), self.agent_index(agent)
        templates = self.vocabulary.templates[self.scenario.kind[i]] if self.vocabulary is not None else None
        return action_towards(
            self.config.action,
            sim.driver.xyh[i, sim.t],
            float(sim.kin.speed[i]),
            target,
            float(self.scenario.size[i, 0]),
            self.config.limits,
            sim.dt,
            templates,
        )

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """The current step as an RGB array (``rgb_array``) or in a window (``human``)."""
        if self.render_mode is None:
            import gymnasium

            gymnasium.logger.warn(
                "render() called without a render_mode; pass render_mode='rgb_array' or 'human'"
            )
            return None
        frame = self._episode_renderer().frame(self._sim().t)
        if self.render_mode == "rgb_array":
            return frame
        self._episode_renderer().show(frame)
        return None

    def _episode_renderer(self) -> Any:
        sim = self._sim()
        if self._renderer is not None and not np.may_share_memory(self._renderer_xyh, sim.driver.xyh):
            self._renderer.close()  # a batched env's engine grew its arrays: draw from the new ones
            self._renderer = None
        if self._renderer is None:
            from trajeglish_env.env.rendering import EpisodeRenderer

            self._renderer_xyh = sim.driver.xyh
            self._renderer = EpisodeRenderer(
                self.scenario,
                sim.driver.xyh,
                sim.driver.valid,
                sim.external,
                sim.npc,
                size=self.config.render_size,
                radius=self.config.render_radius,
            )
        return self._renderer

    def save_video(self, path: str | os.PathLike[str], fps: int | None = None) -> Path:
        """Write the episode so far (from the current index to now) as a GIF or MP4."""
        sim = self._sim()
        return self._episode_renderer().save(path, range(self.scenario.current_index, sim.t + 1), fps or 10)

    def close(self) -> None:
        """Release the renderer and its window."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _resolve_npc(spec: Any) -> tuple[Any, TrajeglishNPC | None, Any]:
    """(NPC policy name/object or checkpoint, Trajeglish settings or None, checkpoint or None) of
    EnvConfig.npc."""
    if spec == "trajeglish":
        spec = TrajeglishNPC()
    if isinstance(spec, TrajeglishNPC):
        ckpt = load_npc_checkpoint(spec.checkpoint)
        return ckpt, spec, ckpt
    if isinstance(spec, str):
        return spec, None, None
    if not isinstance(spec, NPCPolicy):
        raise TypeError(
            f"npc: expected a policy name, a TrajeglishNPC or an object with reset() and act() "
            f"(trajeglish_env.env.npc.NPCPolicy), got {type(spec).__name__}"
        )
    return spec, None, None


def load_npc_checkpoint(checkpoint: Any) -> Any:
    """A checkpoint for Trajeglish NPCs: None -> the shipped model, a path, or a Checkpoint (checked)."""
    from trajeglish_env.checkpoint import (
        Checkpoint,
        CheckpointError,
        check_compatible,
        load_checkpoint,
        load_pretrained,
    )

    if checkpoint is None:
        try:
            return load_pretrained()
        except CheckpointError as exc:
            raise CheckpointError(
                f"{exc}. Trajeglish NPCs need a model: pass npc=TrajeglishNPC(checkpoint=PATH) or a "
                "rule-based NPC policy (npc='idm', 'replay' or 'constant_velocity')"
            ) from exc
    if isinstance(checkpoint, (str, os.PathLike)):
        return load_checkpoint(checkpoint)
    if not isinstance(checkpoint, Checkpoint):
        raise TypeError(f"npc checkpoint: expected a path or a Checkpoint, got {type(checkpoint).__name__}")
    check_compatible(checkpoint.config, checkpoint.vocabulary, where="npc checkpoint")
    return checkpoint


def env(
    scenes: Any = None, config: EnvConfig | None = None, render_mode: str | None = None, **options: Any
) -> AECEnv:
    """The AEC env in PettingZoo's order-enforcing wrapper (actions are checked by the env itself)."""
    return wrappers.OrderEnforcingWrapper(raw_env(scenes, config, render_mode, **options))
