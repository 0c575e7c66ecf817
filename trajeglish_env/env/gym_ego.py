"""Gymnasium single-ego environment (``trajeglish_env/Ego-v0`` and friends) for Stable-Baselines3: one
external agent (the sdc by default) against reactive NPCs, built on the AEC env."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from trajeglish_env.env.aec import raw_env
from trajeglish_env.env.config import EnvConfig, RandomAgents


class EgoEnv(gymnasium.Env):
    """One ego in the AEC env (same arguments as :class:`~trajeglish_env.env.aec.raw_env`; ``external``
    must name a single agent: ``"sdc"``, one track id or ``RandomAgents(1)``).

    Observation, action and reward are those of that agent in the AEC env; ``terminated`` on collision,
    off-road or the end of its route, ``truncated`` at ``max_cycles``. Spawn-safe under SubprocVecEnv (the
    env runs its model calls at ``torch_threads="auto"``: one thread, a second only where a look finds a core
    free of the other workers, the caller's count holding outside them; see EnvConfig.torch_threads).
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        **options: Any,
    ):
        config = (config or EnvConfig()).with_overrides(**options)
        check_single(config)
        self._attach(raw_env(scenes, config, render_mode))

    def _attach(self, aec: raw_env) -> None:
        self.aec = aec
        self.render_mode = aec.render_mode
        self.observation_space = aec.observation_space("ego")
        self.action_space = aec.action_space("ego")
        self.agent = ""

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode (``options["scene"]`` picks the scene); info: the step's keys (zeros now), the
        ego's name and the scene's id."""
        if isinstance(seed, np.integer):
            seed = int(seed)  # numpy integers, as the batched envs take them
        super().reset(seed=seed)  # np_random_seed; np_random is the AEC env's stream, below
        self.aec.reset(seed=seed, options=options)
        self._np_random = self.aec.unwrapped.np_random
        self.agent = self.aec.agents[0]
        return self.aec.observe(self.agent), self._info()

    def _info(self) -> dict[str, Any]:
        """The ego's info: the same keys at reset and at every step (the AEC env's, the ego's name and the
        scene's id)."""
        return {
            **self.aec.infos[self.agent],
            "agent": self.agent,
            "scenario_id": self.aec.scenario.scenario_id,
        }

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One timestep: the ego's action, every NPC's move, the ego's reward and flags."""
        aec, agent = self.aec, self.agent
        if not agent:
            raise RuntimeError("call reset() before step()")
        if aec.terminations[agent] or aec.truncations[agent]:
            raise RuntimeError(f"the episode of {agent} is over; call reset()")
        aec.step(action)
        return (
            aec.observe(agent),
            float(aec._cumulative_rewards[agent]),
            bool(aec.terminations[agent]),
            bool(aec.truncations[agent]),
            self._info(),
        )

    @property
    def np_random(self) -> np.random.Generator:
        """The generator the env draws its scenes and episodes from (the AEC env's episode stream): seeded
        by ``reset(seed=...)``, advanced by every unseeded reset; one set here is drawn from next."""
        return self.aec.unwrapped.np_random

    @np_random.setter
    def np_random(self, value: np.random.Generator) -> None:
        raw = self.aec.unwrapped
        raw.np_random = raw._episodes.np_random = self._np_random = value
        self._np_random_seed = -1  # Gymnasium's mark of a generator set by hand

    # what rule-based and learned ego policies (policies/) read of an AEC env, read through to it: a policy
    # given this env drives its ego as it drives the AEC env's (it failed on 'EgoEnv' has no 'sim')
    @property
    def sim(self) -> Any:
        """The AEC env's simulation."""
        return self.aec.unwrapped.sim

    @property
    def scenario(self) -> Any:
        """The episode's scene."""
        return self.aec.unwrapped.scenario

    @property
    def config(self) -> Any:
        """The env's :class:`~trajeglish_env.env.config.EnvConfig`."""
        return self.aec.unwrapped.config

    def agent_index(self, agent: str) -> int:
        """See :meth:`raw_env.agent_index`."""
        return int(self.aec.unwrapped.agent_index(agent))

    def action_towards(self, agent: str, target: np.ndarray) -> np.ndarray | int:
        """See :meth:`raw_env.action_towards`."""
        return self.aec.unwrapped.action_towards(agent, target)

    def render(self) -> np.ndarray | None:
        """See :meth:`raw_env.render`."""
        return self.aec.render()

    def close(self) -> None:
        """Release the renderer."""
        self.aec.close()


def check_single(config: EnvConfig) -> None:
    """EgoEnv drives exactly one external agent."""
    ext = config.external
    # RandomAgents(1) in any form: one drawn agent, the sdc (with_sdc), or at most one (at_most)
    single = (
        ext == "sdc"
        or (isinstance(ext, tuple) and len(ext) == 1)
        or (isinstance(ext, RandomAgents) and ext.k == 1)
    )
    if not single:
        raise ValueError(
            "EgoEnv controls exactly one agent: external must be 'sdc', one track id or "
            f"RandomAgents(1), got {ext!r} (use trajeglish_env.parallel_env for several)"
        )
