"""Batched environments: ``B`` scenes stepped together in one process on one
:class:`~trajeglish_env.env.scene_batch.SceneBatch` (their Trajeglish NPCs decoded by one engine: one model
call per token position for all B scenes, no subprocesses).

- :class:`BatchedEgoEnv`: a Gymnasium ``VectorEnv`` of B single-ego scenes (same-step autoreset, the final
  observation and info in ``infos["final_obs"]`` / ``infos["final_info"]``).
- :class:`BatchedParallelEnv`: B multi-agent scenes with the PettingZoo parallel API per scene (lists of
  dicts), reset scene by scene with :meth:`BatchedParallelEnv.reset_scenes`.
- :class:`~trajeglish_env.env.sb3.SB3VecEnv`: the ego env as a Stable-Baselines3 ``VecEnv``.

Semantics are those of B separate envs, for every intra-timestep order: scene ``i`` reset with seed ``s``
gives exactly the rollout of ``EgoEnv`` / ``parallel_env`` reset with ``s`` (same scene choices, same NPC
tokens, same observations; each scene keeps its own random stream across autoresets). A step validates
every scene's actions before anything moves; each external agent then acts at its turn in its scene's
order, and observations are taken where the next step's first external agent acts (as in the AEC env).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium
import numpy as np

from trajeglish_env.env.actions import check_action, named_action_space
from trajeglish_env.env.batch_api import EgoVectorEnv, ParallelBatchAPI, check_scene_actions
from trajeglish_env.env.config import EnvConfig
from trajeglish_env.env.episodes import EpisodeStream
from trajeglish_env.env.gym_ego import check_single
from trajeglish_env.env.observations import observation_space
from trajeglish_env.env.scene_batch import SceneBatch
from trajeglish_env.env.scenes import scene_set
from trajeglish_env.env.simulation import AgentReport, Simulation
from trajeglish_env.env.threads import auto_threads
from trajeglish_env.heap import release_freed_memory

__all__ = [
    "BatchedEgoEnv",
    "BatchedParallelEnv",
    "EgoVectorEnv",
    "ParallelBatchAPI",
    "auto_threads",
    "check_scene_actions",
]


class BatchCore:
    """What both batched envs share: the scene batch, each scene's episode stream and renderer, and the
    start / position / observe steps of the protocol."""

    def __init__(
        self,
        num_envs: int,
        scenes: Any,
        config: EnvConfig,
        render_mode: str | None,
        torch_threads: int | str | None,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"batched envs render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.batch = SceneBatch(num_envs, config, torch_threads)
        self.config = self.batch.config
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.scenes = scene_set(scenes)
        self.streams = [EpisodeStream(self.scenes) for _ in range(self.num_envs)]
        self.renderers: list[Any] = []  # one LiveRenderer per scene, made on the first frame (matplotlib)
        self.started = False  # any scene reset yet (render() before reset is an error, as single envs')
        self.single_observation_space = observation_space(config.observation, config.obs)
        vocab = self.batch.vocabulary
        self.vocab_size = vocab.size if vocab is not None else 1

    def start(self, scene: int, seed: int | None, options: dict[str, Any] | None) -> Simulation:
        """Start the next episode of ``scene`` (positioned by the next :meth:`position`)."""
        scenario, rng = self.streams[scene].next(seed, options)
        self.started = True
        return self.batch.start(scene, scenario, rng)

    def position(self) -> None:
        """Let every running scene's NPCs act up to its first external agent of the step."""
        self.batch.advance()

    def sim(self, scene: int) -> Simulation:
        return self.batch.sim(scene)

    def frames(self) -> tuple[np.ndarray | None, ...]:
        """The current frame of every scene (None for a stopped one)."""
        if not self.started:
            raise RuntimeError("call reset() before render()")
        return tuple(self.frame(i) for i in range(self.num_envs))

    def frame(self, scene: int) -> np.ndarray | None:
        """The current frame of scene ``scene`` alone (None when it is stopped)."""
        if not self.renderers:
            from trajeglish_env.render import LiveRenderer

            size, radius, legend = (
                self.config.render_size,
                self.config.render_radius,
                self.config.render_legend,
            )
            self.renderers = [LiveRenderer(size, radius, legend) for _ in range(self.num_envs)]
        sim = self.batch.sims[scene]
        return None if sim is None else self.renderers[scene].of(sim).frame(sim.t)

    def close(self) -> None:
        """Release the renderers (and the engine shards' threads)."""
        for renderer in self.renderers:
            renderer.close()
        close_rows = getattr(self.batch.rows, "close", None)
        if close_rows is not None:
            close_rows()
        release_freed_memory()  # what was freed goes back to the kernel (docs in heap.py)


class EgoScene:
    """Scene ``index`` of a :class:`BatchedEgoEnv`, as far as per-env tools need it (SB3's ``get_attr``,
    ``env_method``, and the external policies of ``policies/``, which read a scene as they read the AEC
    env): its ego's name, simulation and scenario, ``agent_index`` / ``action_towards``, its frame, and a
    reset of this scene alone."""

    spec = None  # as a Gymnasium env not made by gymnasium.make

    def __init__(self, owner: BatchedEgoEnv, index: int):
        self.owner, self.index = owner, index
        self.render_mode = owner.render_mode

    @property
    def np_random(self) -> np.random.Generator:
        """The generator of this scene's episode stream (seeded by its resets)."""
        return self.owner.core.streams[self.index].np_random

    @property
    def unwrapped(self) -> EgoScene:
        return self

    def observation_space(self, agent: str) -> gymnasium.Space:
        """The observation space (PettingZoo-style, as the AEC env)."""
        return self.owner.single_observation_space

    def action_space(self, agent: str) -> gymnasium.Space:
        """The ego's action space (PettingZoo-style, as the AEC env)."""
        return self.owner.single_action_space

    @property
    def agent(self) -> str:
        """The ego's name in the current episode."""
        return self.owner.agents[self.index]

    @property
    def sim(self) -> Simulation:
        """The running simulation of this scene."""
        return self.owner.core.sim(self.index)

    @property
    def scenario(self) -> Any:
        return self.sim.sc

    @property
    def config(self) -> EnvConfig:
        return self.owner.core.config

    @property
    def vocabulary(self) -> Any:
        return self.owner.core.batch.vocabulary

    @property
    def scenes(self) -> Any:
        """The env's scene set."""
        return self.owner.core.scenes

    def agent_index(self, agent: str) -> int:
        """Index in the scene of an external agent's name."""
        return self.sim.index_of(agent)

    def action_towards(self, agent: str, target: np.ndarray) -> np.ndarray | int:
        """The action that brings ``agent`` closest to state ``target [3]`` at the next step."""
        return self.sim.action_towards(self.agent_index(agent), target)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Start this scene's next episode (the others go on where they are)."""
        info = self.owner.restart(self.index, seed, options)
        self.owner.core.position()
        return self.owner.core.batch.observe([self.index], [self.owner.egos[self.index]])[0], info

    def render(self) -> np.ndarray | None:
        return self.owner.core.frame(self.index) if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        """Release this scene's renderer."""
        if self.owner.core.renderers:
            self.owner.core.renderers[self.index].close()


class BatchedEgoEnv(EgoVectorEnv):
    """``num_envs`` single-ego scenes as one Gymnasium ``VectorEnv`` (arguments as
    :class:`~trajeglish_env.env.gym_ego.EgoEnv`, plus ``torch_threads``: an int, None to leave torch
    alone, or ``"auto"``, see :class:`~trajeglish_env.env.threads.AdaptiveThreads`). Autoreset: same step
    (``infos["final_obs"]``)."""

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
        check_single(config)
        self.core = BatchCore(num_envs, scenes, config, render_mode, torch_threads)
        self.num_envs = self.core.num_envs
        self.render_mode = render_mode
        action_space = named_action_space(config.action, self.core.vocab_size, "ego")
        self._set_spaces(self.core.single_observation_space, action_space)
        self.egos = np.zeros(self.num_envs, dtype=np.int64)
        self.agents = [""] * self.num_envs
        self.envs = [EgoScene(self, i) for i in range(self.num_envs)]

    def restart(self, scene: int, seed: int | None, options: dict[str, Any] | None) -> dict[str, Any]:
        """Start scene ``scene``'s next episode; its reset info."""
        sim = self.core.start(scene, seed, options)
        self.egos[scene] = sim.external_index[0]
        self.agents[scene] = sim.names[int(self.egos[scene])]
        return self._info(scene, sim.agent_info(int(self.egos[scene])))

    def _info(self, scene: int, info: dict[str, Any]) -> dict[str, Any]:
        """Scene ``scene``'s ego info: the same keys at reset and at every step, as ``EgoEnv``'s."""
        return {**info, "agent": self.agents[scene], "scenario_id": self.core.sim(scene).sc.scenario_id}

    def reset_each(
        self,
        seeds: Sequence[int | None],
        options: Sequence[dict[str, Any] | None],
        scenes: Sequence[int] | None = None,
    ) -> tuple[list[np.ndarray], list[dict[str, Any]]]:
        """Reset scene i with ``seeds[i]`` and ``options[i]``, for every i of ``scenes`` (None: all); every
        scene's observation and the reset scenes' infos, in scene order."""
        chosen = sorted(range(self.num_envs) if scenes is None else scenes)
        infos = [self.restart(i, seeds[i], options[i]) for i in chosen]
        self.core.position()
        return self._observe_all(), infos

    def _observe_all(self) -> list[np.ndarray]:
        return self.core.batch.observe(range(self.num_envs), self.egos)

    def step_each(self, actions: Any) -> list[tuple[Any, float, bool, bool, dict[str, Any], Any]]:
        """Step every scene; per scene ``(obs, reward, terminated, truncated, info, final)`` where a
        finished scene has been reset (``obs``/``info`` of the new episode) and ``final`` holds the last
        ``(obs, info)`` of the old one (None otherwise)."""
        expected = (self.num_envs, *(self.single_action_space.shape or ()))
        shape = getattr(actions, "shape", None)
        if len(actions) != self.num_envs or (shape is not None and tuple(shape) != expected):
            got = tuple(shape) if shape is not None else f"{len(actions)} actions"
            raise ValueError(
                f"step: expected actions of shape {expected} (one per scene, each in "
                f"{self.single_action_space}), got {got}"
            )
        if not all(self.agents):
            raise RuntimeError("call reset() before step()")
        values = []
        for i, (a, name) in enumerate(zip(actions, self.agents, strict=True)):
            try:
                values.append(check_action(self.single_action_space, a, name))
            except ValueError as exc:  # every highway-env scene has a vehicle_0: name the scene too
                raise ValueError(f"step: scene {i} ({self.core.sim(i).sc.scenario_id}): {exc}") from None
        scenes = range(self.num_envs)
        batch = self.core.batch
        batch.play(scenes, self.egos, values)
        reports = [r[name] for r, name in zip(batch.finish(scenes), self.agents, strict=True)]
        done = [i for i, r in enumerate(reports) if r.terminated or r.truncated]
        finals = dict(zip(done, batch.observe(done, self.egos[done]), strict=True))
        infos = [self._info(i, r.info) for i, r in enumerate(reports)]
        ended = {i: infos[i] for i in done}  # the finished episodes' last infos (their ego and scene)
        for i in done:
            infos[i] = self.restart(i, None, None)
        self.core.position()
        observations = self._observe_all()
        return [
            (
                obs,
                r.reward,
                r.terminated,
                r.truncated,
                info,
                (finals[i], ended[i]) if i in finals else None,
            )
            for i, (obs, r, info) in enumerate(zip(observations, reports, infos, strict=True))
        ]

    def apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> list[Any]:
        """``[fn(self, *args, **kwargs)]``: this env as the one shard of its scenes (the API of
        :meth:`~trajeglish_env.env.split.SplitEgoEnv.apply`, whose scenes live in several)."""
        return [fn(self, *args, **kwargs)]

    def render(self) -> tuple[Any, ...] | None:
        """Frames of every scene (``rgb_array``)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        return self.core.frames()

    def close_extras(self, **kwargs: Any) -> None:
        """Release the renderers."""
        self.core.close()


class BatchedParallelEnv(ParallelBatchAPI):
    """``num_envs`` multi-agent scenes stepped together, each with the PettingZoo parallel API (same
    arguments as :func:`~trajeglish_env.env.parallel.parallel_env`, plus ``torch_threads``).

    ``reset`` / ``reset_scenes`` / ``step`` take and return lists with one entry per scene (dicts keyed
    by agent name, as a parallel env). A scene whose agents are all done stays empty (empty dicts, no
    decoding) until :meth:`reset_scenes` restarts it.
    """

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
        self.core = BatchCore(num_envs, scenes, config, render_mode, torch_threads)
        self.num_envs = self.core.num_envs
        self.render_mode = render_mode
        self.agents: list[list[str]] = [[] for _ in range(self.num_envs)]
        self.episode_agents: list[set[str]] = [set() for _ in range(self.num_envs)]  # live or finished
        self._scenario_ids: list[str | None] = [None] * self.num_envs  # each scene's, from its last reset
        self._observation = self.core.single_observation_space
        self._actions = (self.core.config.action, self.core.vocab_size)

    def _reset_scenes(
        self, indices: list[int], seeds: list[int | None], options: dict[str, Any] | None
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        for i, s in zip(indices, seeds, strict=True):
            self.core.start(i, s, options)
        self.core.position()
        observations, infos = [], []
        for i in indices:
            sim = self.core.sim(i)
            self.agents[i] = [sim.names[a] for a in sim.external_order()]
            self.episode_agents[i] = set(self.agents[i])
            self._scenario_ids[i] = sim.sc.scenario_id
            observations.append(self._observe(i, self.agents[i]))
            infos.append({sim.names[a]: sim.agent_info(a) for a in sim.external_order()})
        return observations, infos

    def sim(self, scene: int) -> Simulation:
        """Scene ``scene``'s running simulation (``sim(i).view()``: every agent's state, e.g. for a
        centralised critic; a RuntimeError for a scene whose agents have all finished, until it is reset)."""
        return self.core.sim(scene)

    def _observe(self, scene: int, names: Sequence[str]) -> dict[str, np.ndarray]:
        sim = self.core.sim(scene)
        index = {sim.names[a]: int(a) for a in sim.external_index}
        obs = self.core.batch.observe([scene] * len(names), [index[n] for n in names])
        return dict(zip(names, obs, strict=True))

    def _validated(self, actions: Sequence[dict[str, Any]]) -> tuple[list[int], list[int], list[Any]]:
        """Every scene's actions checked (:func:`check_scene_actions`) before anything moves: the flat
        (scenes, agents, actions) to play."""
        scenes, agents, values = [], [], []
        checks = check_scene_actions(
            self.agents, actions, self.action_space, self.episode_agents, self._scenario_ids
        )
        for i, checked in enumerate(checks):
            if not checked:
                continue
            sim = self.core.sim(i)
            index = {sim.names[a]: int(a) for a in sim.external_index}
            for name, value in zip(self.agents[i], checked, strict=True):
                scenes.append(i)
                agents.append(index[name])
                values.append(value)
        return scenes, agents, values

    def step(self, actions: Sequence[dict[str, Any]]) -> tuple[list[dict[str, Any]], ...]:
        """One timestep of every scene that has agents: ``actions[i]`` maps scene i's agents to actions.
        Returns per-scene lists of observations, rewards, terminations, truncations and infos."""
        scenes, agents, values = self._validated(actions)
        busy = [i for i in range(self.num_envs) if self.agents[i]]
        batch = self.core.batch
        batch.play(scenes, agents, values)
        reports = dict(zip(busy, batch.finish(busy), strict=True))
        out: tuple[list[dict[str, Any]], ...] = tuple([{} for _ in range(self.num_envs)] for _ in range(5))
        ended = [i for i in busy if not self.core.sim(i).has_live_agents]
        for i in ended:  # observed as the step left them, then their rows stop
            self._fill(out, i, reports[i])
            batch.stop(i)
            self.agents[i] = []
        self.core.position()
        for i in busy:
            if i not in ended:
                self._fill(out, i, reports[i])
                sim = self.core.sim(i)
                self.agents[i] = [sim.names[a] for a in sim.external_order()]
        return out

    def _fill(
        self, out: tuple[list[dict[str, Any]], ...], scene: int, reports: dict[str, AgentReport]
    ) -> None:
        """Scene ``scene``'s entries of a step's results."""
        out[0][scene].update(self._observe(scene, list(reports)))
        for name, r in reports.items():
            out[1][scene][name] = r.reward
            out[2][scene][name] = r.terminated
            out[3][scene][name] = r.truncated
            out[4][scene][name] = r.info

    def render(self) -> tuple[Any, ...] | None:
        """Frames of every scene (``rgb_array``; None for a finished scene)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        return self.core.frames()

    def apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> list[Any]:
        """``[fn(self, *args, **kwargs)]``: this env as the one shard of its scenes (see
        :meth:`~trajeglish_env.env.split.SplitParallelEnv.apply`)."""
        return [fn(self, *args, **kwargs)]

    def close(self) -> None:
        """Release the renderers."""
        self.core.close()
