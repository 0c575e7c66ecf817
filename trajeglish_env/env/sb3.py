"""The batched ego env as a Stable-Baselines3 ``VecEnv``: SB3 trains on B scenes whose NPCs are decoded
together, in one process or split over worker processes (no SubprocVecEnv needed)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from trajeglish_env.env.config import EnvConfig
from trajeglish_env.env.split import batched_ego_env


class SB3VecEnv(VecEnv):
    """``num_envs`` ego scenes (arguments as :class:`~trajeglish_env.env.vector.BatchedEgoEnv`) with SB3's
    conventions: ``dones = terminated | truncated``, same-step reset with ``infos[i]["terminal_observation"]``
    and ``infos[i]["TimeLimit.truncated"]``, seeds from :meth:`seed` (``seed + i``) used at the next reset.

    ``processes``: the scenes split over that many forked worker processes
    (:class:`~trajeglish_env.env.split.SplitEgoEnv`, the same rollouts); ``"auto"`` (default): one per core
    that other processes leave free, at least 4 scenes each, else one process (Linux only)."""

    def __init__(
        self,
        num_envs: int,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        torch_threads: int | str | None = "auto",
        processes: int | str = "auto",
        **options: Any,
    ):
        self.venv = batched_ego_env(
            num_envs, scenes, config, render_mode, torch_threads, processes, **options
        )
        self.envs = self.venv.envs
        self._actions: np.ndarray | None = None
        super().__init__(num_envs, self.venv.single_observation_space, self.venv.single_action_space)

    def reset(self) -> np.ndarray:
        """Reset every scene (with the seeds and options set for this reset, if any)."""
        obs, self.reset_infos = self.venv.reset_each(self._seeds, [o or None for o in self._options])
        self._reset_seeds()
        self._reset_options()
        return np.stack(obs)

    def step_async(self, actions: np.ndarray) -> None:
        """Store the actions of the next step."""
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        """Step every scene at once (NPCs of all scenes decoded together)."""
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async()")
        results = self.venv.step_each(self._actions)
        self._actions = None
        obs, rewards, dones, infos = (
            [],
            np.zeros(self.num_envs, dtype=np.float32),
            np.zeros(self.num_envs, bool),
            [],
        )
        for i, (o, reward, terminated, truncated, info, final) in enumerate(results):
            info = dict(info if final is None else final[1])  # at an episode's end: its last step's info
            rewards[i], dones[i] = reward, terminated or truncated
            info["TimeLimit.truncated"] = bool(truncated and not terminated)
            if final is not None:
                info["terminal_observation"] = final[0]
                self.reset_infos[i] = dict(results[i][4])
            obs.append(o)
            infos.append(info)
        return np.stack(obs), rewards, dones, infos

    def close(self) -> None:
        """Release the renderers (and stop the worker processes)."""
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One frame per scene (``render_mode="rgb_array"``)."""
        return [env.render() for env in self.envs]

    def _targets(self, indices: VecEnvIndices) -> list[Any]:
        return [self.envs[i] for i in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """An attribute of each (or the given) scene env; ``observation_space`` / ``action_space`` are the
        scene's spaces, as SB3's own vector envs give them (a scene object offers them PettingZoo-style,
        as methods of the agent)."""
        targets = self._targets(indices)
        if attr_name in ("observation_space", "action_space"):
            return [getattr(self, attr_name) for _ in targets]
        return [getattr(env, attr_name) for env in targets]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute of each (or the given) scene env."""
        for env in self._targets(indices):
            setattr(env, attr_name, value)

    def env_method(
        self, method_name: str, *args: Any, indices: VecEnvIndices = None, **kwargs: Any
    ) -> list[Any]:
        """Call a method of each (or the given) scene env."""
        return [getattr(env, method_name)(*args, **kwargs) for env in self._targets(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        """The scene envs are never wrapped."""
        return [False for _ in self._targets(indices)]
