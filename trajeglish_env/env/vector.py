"""Batched environments: ``B`` scenes stepped together in one process, their Trajeglish NPCs decoded by
one :class:`~trajeglish_env.sampler.engine.BatchEngine` (one model call per token position for all B
scenes, no subprocesses).

- :class:`BatchedEgoEnv`: a Gymnasium ``VectorEnv`` of B single-ego envs (same-step autoreset, the final
  observation and info in ``infos["final_obs"]`` / ``infos["final_info"]``).
- :class:`BatchedParallelEnv`: B multi-agent scenes with the PettingZoo parallel API per scene (lists of
  dicts), reset scene by scene with :meth:`BatchedParallelEnv.reset_scenes`.
- :class:`SB3VecEnv`: the ego env as a Stable-Baselines3 ``VecEnv`` (``terminal_observation`` infos).

Semantics are those of B separate envs: scene ``i`` reset with seed ``s`` gives exactly the rollout of
``EgoEnv`` / ``parallel_env`` reset with ``s`` (same scene choices, same NPC tokens; each sub-env keeps
its own random stream across autoresets). Every step, each scene first applies its external agents'
actions, then the NPCs of all scenes are decoded together; this is the ``order="first"`` intra-timestep
order (external agents act before every NPC), the only order a batched env supports.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array
from gymnasium.vector.vector_env import AutoresetMode

from trajeglish_env.env.aec import raw_env
from trajeglish_env.env.batch_outcomes import BatchGeometry
from trajeglish_env.env.config import EnvConfig, TrajeglishNPC
from trajeglish_env.env.gym_ego import EgoEnv
from trajeglish_env.env.simulation import apply_actions


def auto_threads(num_envs: int) -> int:
    """Torch threads for a batch: 1 for a few scenes (small calls are fastest single-threaded), then one
    per 4 scenes up to the cores this process may use."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(cores, num_envs // 4))


def _seeds(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """Per-env seeds as Gymnasium's vector envs derive them (``seed + i``, or a list of n seeds)."""
    if seed is None or isinstance(seed, (int, np.integer)):
        return [None if seed is None else int(seed) + i for i in range(n)]
    seeds = list(seed)
    if len(seeds) != n:
        raise ValueError(f"reset: expected {n} seeds (one per scene), got {len(seeds)}")
    return seeds


class SceneBatch:
    """``num_envs`` AEC envs on one scene set whose Trajeglish NPCs share one engine (row i = env i).

    Step protocol: every env applies its external agents' actions (their AEC steps end *suspended*),
    :meth:`decode` decodes every scene's NPCs at once, then each suspended env is resumed.
    """

    def __init__(
        self,
        num_envs: int,
        scenes: Any,
        config: EnvConfig,
        render_mode: str | None,
        torch_threads: int | str | None = "auto",
    ):
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if not (torch_threads in ("auto", None) or (isinstance(torch_threads, int) and torch_threads >= 1)):
            raise ValueError(
                f"torch_threads must be 'auto', None or a positive integer, got {torch_threads!r}"
            )
        first = raw_env(scenes, config, render_mode)
        if first.checkpoint is not None:
            if config.order != "first":
                raise ValueError(
                    f"batched envs need order='first' (external agents act before every NPC, so the NPCs of "
                    f"all scenes are decoded together); got order={config.order!r}. Use the unbatched envs "
                    "for other intra-timestep orders"
                )
            settings = first._sampling if isinstance(first._sampling, TrajeglishNPC) else TrajeglishNPC()
            config = config.with_overrides(npc=replace(settings, checkpoint=first.checkpoint))  # load once
        shared_scenes = first.scenes
        self.envs = [first] + [raw_env(shared_scenes, config, render_mode) for _ in range(num_envs - 1)]
        self.geometry = BatchGeometry()
        self.engine = None
        if first.checkpoint is not None:
            import torch

            from trajeglish_env.sampler.engine import BatchEngine

            threads = auto_threads(num_envs) if torch_threads == "auto" else torch_threads
            if threads is not None:
                torch.set_num_threads(int(threads))
            self.engine = BatchEngine(
                first.checkpoint, num_envs, settings.sampling(), settings.torch_cache_dtype
            )
            for i, env in enumerate(self.envs):
                env._shared_row = (self.engine, i)

    def decode(self) -> None:
        """Decode this step's NPCs of every suspended scene, then resume those scenes (their step outcomes
        computed for all of them at once)."""
        waiting = [env for env in self.envs if env.suspended]
        if self.engine is not None and waiting:
            self.engine.step()
        if waiting:
            sims = [env._sim() for env in waiting]
            for sim, outcome in zip(sims, self.geometry.outcomes(sims), strict=True):
                sim.prepared = (sim.t, outcome)
        for env in waiting:
            env.resume()

    def observe(self, envs: Sequence[raw_env], agents: Sequence[str]) -> list[np.ndarray]:
        """Observations of agent ``agents[i]`` of ``envs[i]`` now, computed together for ``vector``
        observations (see :mod:`~trajeglish_env.env.batch_geometry`)."""
        if not envs:
            return []
        if self.envs[0].config.observation != "vector":
            return [env.observe(agent) for env, agent in zip(envs, agents, strict=True)]
        sims = [env._sim() for env in envs]
        index = [env.agent_index(agent) for env, agent in zip(envs, agents, strict=True)]
        return list(self.geometry.observations(sims, index))

    def stop(self, index: int) -> None:
        """Scene ``index`` has no agents left: its engine row stops decoding until the scene is reset."""
        if self.engine is not None:
            self.engine.stop_rows([index])


class BatchedEgoEnv(VectorEnv):
    """``num_envs`` single-ego scenes as one Gymnasium ``VectorEnv`` (arguments as
    :class:`~trajeglish_env.env.gym_ego.EgoEnv`, plus ``torch_threads``: an int, None to leave torch
    alone, or ``"auto"``, see :func:`auto_threads`). Autoreset: same step (``infos["final_obs"]``)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        num_envs: int,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        torch_threads: int | str | None = "auto",
        **options: Any,
    ):
        config = (config or EnvConfig()).with_overrides(**options)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"BatchedEgoEnv render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.batch = SceneBatch(num_envs, scenes, config, render_mode, torch_threads)
        self.envs = [EgoEnv.around(aec) for aec in self.batch.envs]
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._obs = create_empty_array(self.single_observation_space, self.num_envs)
        self._single_obs: list[Any] = [None] * self.num_envs

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every scene (``seed + i`` for scene i, or a list of seeds; ``options`` go to each)."""
        self._np_random_seed = seed if isinstance(seed, int) else None
        infos: dict[str, Any] = {}
        for i, (env, s) in enumerate(zip(self.envs, _seeds(seed, self.num_envs), strict=True)):
            self._single_obs[i], info = env.reset(seed=s, options=options)
            infos = self._add_info(infos, info, i)
        return self._batched_obs(), infos

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One timestep of every scene; finished scenes are reset in the same call."""
        rewards = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        infos: dict[str, Any] = {}
        for i, (obs, rewards[i], terminated[i], truncated[i], info, final) in enumerate(
            self.step_each(actions)
        ):
            if final is not None:
                infos = self._add_info(infos, {"final_obs": final[0], "final_info": final[1]}, i)
            self._single_obs[i] = obs
            infos = self._add_info(infos, info, i)
        return self._batched_obs(), rewards, terminated, truncated, infos

    def step_each(self, actions: Any) -> list[tuple[Any, float, bool, bool, dict[str, Any], Any]]:
        """Step every scene; per scene ``(obs, reward, terminated, truncated, info, final)`` where a
        finished scene has been reset (``obs``/``info`` of the new episode) and ``final`` holds the last
        ``(obs, info)`` of the old one (None otherwise)."""
        if len(actions) != self.num_envs:
            raise ValueError(f"step: expected {self.num_envs} actions (one per scene), got {len(actions)}")
        prepared = [env.prepare(action) for env, action in zip(self.envs, actions, strict=True)]
        apply_actions(*zip(*prepared, strict=True))  # every action is valid before any is applied
        for env in self.envs:
            env.aec.after_action()
        self.batch.decode()
        observations = self.batch.observe([env.aec for env in self.envs], [env.agent for env in self.envs])
        results = []
        for env, observation in zip(self.envs, observations, strict=True):
            obs, reward, terminated, truncated, info = env.outcome(observation)
            final = None
            if terminated or truncated:
                final = (obs, info)
                obs, info = env.reset()
            results.append((obs, reward, terminated, truncated, info, final))
        return results

    def _batched_obs(self) -> Any:
        return concatenate(self.single_observation_space, self._single_obs, self._obs).copy()

    def render(self) -> tuple[Any, ...] | None:
        """Frames of every scene (``rgb_array``)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        """Release the renderers."""
        for env in self.envs:
            env.close()


class BatchedParallelEnv:
    """``num_envs`` multi-agent scenes stepped together, each with the PettingZoo parallel API (same
    arguments as :func:`~trajeglish_env.env.parallel.parallel_env`, plus ``torch_threads``).

    ``reset`` / ``reset_scenes`` / ``step`` take and return lists with one entry per scene (dicts keyed
    by agent name, as a parallel env). A scene whose agents are all done stays empty (empty dicts, no
    decoding) until :meth:`reset_scenes` restarts it.
    """

    metadata = {"name": "trajeglish_batched_v0", "render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        num_envs: int,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        torch_threads: int | str | None = "auto",
        **options: Any,
    ):
        config = (config or EnvConfig()).with_overrides(**options)
        self.batch = SceneBatch(num_envs, scenes, config, render_mode, torch_threads)
        self.envs = self.batch.envs
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.agents: list[list[str]] = [[] for _ in range(self.num_envs)]

    def observation_space(self, agent: str) -> gymnasium.Space:
        """The observation space (the same for every agent of every scene)."""
        return self.envs[0].observation_space(agent)

    def action_space(self, agent: str) -> gymnasium.Space:
        """The agent's action space (as in the parallel env)."""
        return self.envs[0].action_space(agent)

    def reset(
        self, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """Reset every scene (``seed + i`` for scene i, or a list of seeds)."""
        return self.reset_scenes(range(self.num_envs), seed, options)

    def reset_scenes(
        self,
        indices: Sequence[int],
        seed: int | list[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """Reset the scenes ``indices`` (seeds as :meth:`reset`, per listed scene); returns their
        observations and infos, in that order."""
        indices = [int(i) for i in indices]
        bad = [i for i in indices if not 0 <= i < self.num_envs]
        if bad:
            raise ValueError(f"reset_scenes: scene indices {bad} out of range for {self.num_envs} scenes")
        observations, infos = [], []
        for i, s in zip(indices, _seeds(seed, len(indices)), strict=True):
            env = self.envs[i]
            env.reset(seed=s, options=options)
            self.agents[i] = env.agents[:]
            observations.append(
                {a: env.observe(a) for a in env.agents if not (env.terminations[a] or env.truncations[a])}
            )
            infos.append(dict(**env.infos))
        return observations, infos

    def step(self, actions: Sequence[dict[str, Any]]) -> tuple[list[dict[str, Any]], ...]:
        """One timestep of every scene that has agents: ``actions[i]`` maps scene i's agents to actions.
        Returns per-scene lists of observations, rewards, terminations, truncations and infos."""
        if len(actions) != self.num_envs:
            raise ValueError(
                f"step: expected {self.num_envs} action dicts (one per scene), got {len(actions)}"
            )
        rewards: list[dict[str, float]] = [{} for _ in range(self.num_envs)]
        busy = [i for i in range(self.num_envs) if self.envs[i].agents]
        for i in busy:
            env = self.envs[i]
            missing = [a for a in env.agents if a not in actions[i]]
            if missing:
                raise KeyError(f"step: scene {i} has no action for agent(s) {missing}")
            for agent in env.agents:
                env.step(actions[i][agent])
                if not env.suspended:
                    _add_rewards(rewards[i], env)
        resumed = {i for i in busy if self.envs[i].suspended}
        self.batch.decode()
        out: tuple[list[dict[str, Any]], ...] = tuple([{} for _ in range(self.num_envs)] for _ in range(5))
        for i in busy:
            env = self.envs[i]
            if i in resumed:
                _add_rewards(rewards[i], env)
            out[0][i].update({a: env.observe(a) for a in env.agents})
            out[1][i].update(rewards[i])
            out[2][i].update(env.terminations)
            out[3][i].update(env.truncations)
            out[4][i].update(env.infos)
            while env.agents and (
                env.terminations[env.agent_selection] or env.truncations[env.agent_selection]
            ):
                env.step(None)
            self.agents[i] = env.agents[:]
            if not env.agents:
                self.batch.stop(i)
        return out

    def render(self) -> tuple[Any, ...]:
        """Frames of every scene (``rgb_array``)."""
        return tuple(env.render() for env in self.envs)

    def close(self) -> None:
        """Release the renderers."""
        for env in self.envs:
            env.close()


def _add_rewards(total: dict[str, float], env: raw_env) -> None:
    """Accumulate this AEC step's rewards of every agent (as PettingZoo's aec_to_parallel does)."""
    for agent in env.agents:
        total[agent] = total.get(agent, 0) + env.rewards[agent]
