"""The API shapes the batched envs share, whether their scenes live in this process
(:mod:`~trajeglish_env.env.vector`) or in worker processes (:mod:`~trajeglish_env.env.split`): per-scene
seeds, the checks of a step's actions, and the Gymnasium ``VectorEnv`` and per-scene parallel APIs built
on each env's own per-scene steps."""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array
from gymnasium.vector.vector_env import AutoresetMode

from trajeglish_env.env.actions import check_action, named_action_space

__all__ = [
    "EgoVectorEnv",
    "ParallelBatchAPI",
    "check_scene_actions",
    "reset_mask",
    "scene_indices",
    "scene_seeds",
]


def scene_seeds(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """Per-scene seeds as Gymnasium's vector envs derive them (``seed + i``, or a list of n seeds), each a
    non-negative integer or None; checked before any scene restarts (a refused reset changes nothing)."""
    if seed is None or isinstance(seed, (int, np.integer)):
        seeds: list[Any] = [None if seed is None else int(seed) + i for i in range(n)]
    else:
        seeds = list(seed)
    if len(seeds) != n:
        raise ValueError(f"reset: expected {n} seeds (one per scene), got {len(seeds)}")
    for i, s in enumerate(seeds):
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0):
            raise ValueError(f"reset: scene {i}'s seed must be a non-negative integer or None, got {s!r}")
    return [None if s is None else int(s) for s in seeds]


def reset_mask(mask: Any, n: int) -> np.ndarray | None:
    """``options["reset_mask"]`` checked as Gymnasium's vector envs check it: None, or a bool array of
    shape ``(n,)`` with at least one True."""
    if mask is None:
        return None
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
        raise TypeError(f"reset: options['reset_mask'] must be a NumPy bool array, got {mask!r}")
    if mask.shape != (n,):
        raise ValueError(f"reset: options['reset_mask'] must have shape ({n},), got {mask.shape}")
    if not mask.any():
        raise ValueError("reset: options['reset_mask'] resets no scene (at least one True expected)")
    return mask


def scene_indices(indices: Iterable[int], n: int) -> list[int]:
    """``reset_scenes``' scene indices as ints, checked before any scene restarts: a sequence of distinct
    integers in [0, n) (bools, floats, a lone int are a TypeError; out of range or repeated a ValueError)."""
    want = f"integers in [0, {n})"
    if (
        isinstance(indices, (int, np.integer, str, bytes, Mapping))
        or not isinstance(indices, Iterable)
        or (isinstance(indices, np.ndarray) and indices.ndim != 1)
    ):
        hint = f"; for one scene pass [{int(indices)}]" if isinstance(indices, (int, np.integer)) else ""
        raise TypeError(
            f"reset_scenes: expected a sequence of scene indices ({want}), got "
            f"{type(indices).__name__} {indices!r}{hint}"
        )
    out = []
    for k in indices:
        if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
            raise TypeError(
                f"reset_scenes: scene index {k!r} ({type(k).__name__}) is not an integer; expected {want}"
            )
        out.append(int(k))
    bad = [k for k in out if not 0 <= k < n]
    if bad:
        raise ValueError(f"reset_scenes: scene indices {bad} out of range for {n} scenes; expected {want}")
    if len(set(out)) != len(out):
        repeated = sorted({k for k in out if out.count(k) > 1})
        raise ValueError(f"reset_scenes: scene indices {repeated} listed more than once in {out}")
    return out


def check_scene_actions(
    agents: Sequence[Sequence[str]],
    actions: Sequence[dict[str, Any]],
    action_space: Callable[[str], gymnasium.Space],
    episode_agents: Sequence[Collection[str]] | None = None,
    scenario_ids: Sequence[str | None] | None = None,
) -> list[list[Any]]:
    """Per scene (its live agents ``agents[i]``), the checked values of ``actions[i]``, in agent order: one
    action per live agent, no unknown agent, each inside its space; the first problem raised, naming the
    scene (and its scenario, ``scenario_ids[i]``, where given) and the agent. ``actions`` is a list (or
    tuple) of one dict per scene (one dict alone is a TypeError). Actions for agents of the episode that
    have finished (``episode_agents[i]``) are ignored, as PettingZoo's parallel envs ignore them."""
    n = len(agents)
    if isinstance(actions, (Mapping, str, bytes)) or not isinstance(actions, Sequence):
        hint = " (a dict agent name -> action is one scene's actions: pass one such dict per scene)"
        raise TypeError(
            f"step: expected a list of {n} action dicts (one per scene), got a {type(actions).__name__}"
            + (hint if isinstance(actions, Mapping) else "")
        )
    if len(actions) != n:
        raise ValueError(f"step: expected {n} action dicts (one per scene), got {len(actions)}")
    out = []
    for i, names in enumerate(agents):
        given = actions[i]
        if not isinstance(given, Mapping):
            raise TypeError(
                f"step: scene {i}'s actions must be a dict agent name -> action, got {type(given).__name__}"
            )
        if names:
            missing = [a for a in names if a not in given]
            unknown = sorted(
                map(str, set(given) - set(names) - set(episode_agents[i] if episode_agents else ()))
            )
            if missing:
                also = f"; actions were given for {unknown}, which are no agents of it" if unknown else ""
                raise KeyError(f"step: scene {i} has no action for agent(s) {missing}{also}")
            if unknown:
                raise KeyError(
                    f"step: scene {i} has no live agent(s) {unknown}; its agents are {list(names)}"
                )
        try:
            out.append([check_action(action_space(name), given[name], name) for name in names])
        except ValueError as exc:  # agent names repeat across scenes: name the scene too
            scene = f"scene {i} ({scenario_ids[i]})" if scenario_ids and scenario_ids[i] else f"scene {i}"
            raise ValueError(f"step: {scene}: {exc}") from None
    return out


class EgoVectorEnv(VectorEnv):
    """The Gymnasium ``VectorEnv`` API of the batched ego envs
    (:class:`~trajeglish_env.env.vector.BatchedEgoEnv` and :class:`~trajeglish_env.env.split.SplitEgoEnv`)
    on their per-scene ``reset_each`` / ``step_each``.
    Autoreset: same step (``infos["final_obs"]``)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"], "render_fps": 10}
    _obs: Any

    def reset_each(
        self,
        seeds: Sequence[int | None],
        options: Sequence[dict[str, Any] | None],
        scenes: Sequence[int] | None = None,
    ) -> tuple[list[np.ndarray], list[dict[str, Any]]]:
        """Reset scene i with ``seeds[i]`` / ``options[i]`` for every i of ``scenes`` (None: all): every
        scene's observation, the reset scenes' infos in scene order."""
        raise NotImplementedError

    def step_each(self, actions: Any) -> list[tuple[Any, float, bool, bool, dict[str, Any], Any]]:
        """Step every scene with its action: per scene (obs, reward, terminated, truncated, info, final)."""
        raise NotImplementedError

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every scene (``seed + i`` for scene i, or a list of seeds; ``options`` go to each), or
        those of ``options["reset_mask"]`` (a bool array, one per scene, as Gymnasium's vector envs take it:
        the others go on; infos only of the reset ones)."""
        seeds = scene_seeds(seed, self.num_envs)
        options = dict(options) if options is not None else None
        mask = reset_mask(options.pop("reset_mask", None) if options is not None else None, self.num_envs)
        if isinstance(seed, (int, np.integer)):  # VectorEnv.reset's seeding of np_random
            self._np_random, self._np_random_seed = seeding.np_random(int(seed))
        scenes = list(range(self.num_envs)) if mask is None else np.flatnonzero(mask).tolist()
        observations, infos = self.reset_each(seeds, [options] * self.num_envs, scenes)
        merged: dict[str, Any] = {}
        for i, info in zip(scenes, infos, strict=True):
            merged = self._add_info(merged, info, i)
        return self._batched(observations), merged

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One timestep of every scene; finished scenes are reset in the same call."""
        rewards = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        infos: dict[str, Any] = {}
        observations = []
        for i, (obs, rewards[i], terminated[i], truncated[i], info, final) in enumerate(
            self.step_each(actions)
        ):
            if final is not None:
                infos = self._add_info(infos, {"final_obs": final[0], "final_info": final[1]}, i)
            observations.append(obs)
            infos = self._add_info(infos, info, i)
        return self._batched(observations), rewards, terminated, truncated, infos

    def _set_spaces(self, observation: gymnasium.Space, action: gymnasium.Space) -> None:
        """One scene's observation and action spaces, and those of the batch (``num_envs`` set first)."""
        self.single_observation_space, self.single_action_space = observation, action
        self.observation_space = batch_space(observation, self.num_envs)
        self.action_space = batch_space(action, self.num_envs)
        self._obs = create_empty_array(observation, self.num_envs)

    def _batched(self, observations: list[np.ndarray]) -> Any:
        return concatenate(self.single_observation_space, observations, self._obs).copy()


class ParallelBatchAPI:
    """What the batched parallel envs (:class:`BatchedParallelEnv` and
    :class:`~trajeglish_env.env.split.SplitParallelEnv`) share: the spaces (``_observation`` and the action
    type and vocabulary size of ``_actions``, set by the subclass), ``reset``, and ``reset_scenes`` checking
    its scene indices before ``_reset_scenes`` restarts them."""

    metadata = {"name": "trajeglish_batched_v0", "render_modes": ["rgb_array"], "render_fps": 10}
    num_envs: int
    _observation: gymnasium.Space
    _actions: tuple[str, int]

    def observation_space(self, agent: str) -> gymnasium.Space:
        """The observation space (the same for every agent of every scene)."""
        return self._observation

    def action_space(self, agent: str) -> gymnasium.Space:
        """The agent's action space (as in the parallel env: its sampling seeded from the name)."""
        spaces: dict[str, gymnasium.Space] = self.__dict__.setdefault("_action_spaces", {})
        if agent not in spaces:
            spaces[agent] = named_action_space(*self._actions, agent)
        return spaces[agent]

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
        """Reset the scenes ``indices`` (a list of distinct scene indices, checked by :func:`scene_indices`;
        seeds as :meth:`reset`, per listed scene); returns their observations and infos, in that order."""
        indices = scene_indices(indices, self.num_envs)
        return self._reset_scenes(indices, scene_seeds(seed, len(indices)), options)

    def _reset_scenes(
        self, indices: list[int], seeds: list[int | None], options: dict[str, Any] | None
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        raise NotImplementedError
