"""Learned policies for external agents: a trained Stable-Baselines3 model, and the Trajeglish model itself
driving an agent (sampling its next token given everything decided so far in the step)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from trajeglish_env.sampler.config import SamplingConfig


class SB3Policy:
    """Wraps any trained SB3 model (``model.predict``); one instance can drive one or many agents."""

    def __init__(self, model: Any, deterministic: bool = True):
        self.model = model
        self.deterministic = deterministic

    def reset(self, env: Any, agent: str) -> None:
        """Prepare for a new episode of ``agent``."""
        return None

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The action of ``agent`` at its turn."""
        action, _ = self.model.predict(observation, deterministic=self.deterministic)
        return int(action) if np.ndim(action) == 0 else np.asarray(action, dtype=np.float32)

    def act_many(self, observations: dict[str, np.ndarray]) -> dict[str, Any]:
        """Actions for several agents in one batched forward pass."""
        names = list(observations)
        if not names:
            return {}
        actions, _ = self.model.predict(
            np.stack([observations[a] for a in names]), deterministic=self.deterministic
        )
        return {
            a: (int(x) if np.ndim(x) == 0 else np.asarray(x, dtype=np.float32))
            for a, x in zip(names, actions, strict=True)
        }


class TrajeglishPolicy:
    """The Trajeglish model driving an external agent: at the agent's turn it samples the agent's next token
    conditioned on every agent's history and on the moves already made in this step (those after it are
    unknown to it), then takes the env action that best reaches the sampled state.

    It re-encodes the scene at every call (exact but slow: a demonstration and an evaluation baseline).
    """

    def __init__(self, checkpoint: Any = None, sampling: SamplingConfig | None = None):
        from trajeglish_env.env.scene_batch import load_npc_checkpoint

        self.ckpt = load_npc_checkpoint(checkpoint)
        self.sampling = sampling or SamplingConfig()  # the env's NPC defaults; its seed starts the calls
        self._calls = 0
        self._episode_seed = 0

    def reset(self, env: Any, agent: str) -> None:
        """Prepare for a new episode of ``agent``: its draws follow the episode's seed (so the same env seed
        and scene give the same episode, whatever this policy played before)."""
        raw = env.unwrapped
        self._calls, self._episode_seed = 0, int(getattr(raw.sim, "seed", 0))
        vocab = getattr(raw, "vocabulary", None)
        if raw.config.action == "token" and vocab is not None and not vocab.equals(self.ckpt.vocabulary):
            raise ValueError(
                f"TrajeglishPolicy for {agent}: the checkpoint's vocabulary ({self.ckpt.vocabulary.size} "
                f"templates, {self.ckpt.vocabulary.method}) does not match the env's token vocabulary "
                f"({vocab.size} templates, {vocab.method}); token actions would mean different motions"
            )

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The action of ``agent`` at its turn."""
        from trajeglish_env.sampler.engine import RolloutEngine

        raw = env.unwrapped
        sim, i = raw.sim, raw.agent_index(agent)
        view = sim.view()
        t = view.t
        xyh = view.xyh[:, : t + 2].copy()
        valid = view.valid[:, : t + 2].copy()
        valid[:, t + 1] &= view.moved  # only the moves already decided in this step
        valid[i, t + 1] = False
        scene = _truncated_scene(raw.scenario, xyh, valid, t, i)
        controlled = np.zeros(scene.num_agents, dtype=bool)
        controlled[i] = True
        priority = np.where(view.moved, -2.0, 0.0)
        priority[i] = -1.0
        seed = np.random.SeedSequence([self.sampling.seed, self._episode_seed, self._calls]).generate_state(1)
        config = dataclasses.replace(self.sampling, seed=int(seed[0] >> 1))
        self._calls += 1
        engine = RolloutEngine(self.ckpt, scene, 1, 1, controlled, priority=priority, config=config)
        engine.step()
        return raw.action_towards(agent, engine.xyh[0, i, t + 1])


def _truncated_scene(scenario: Any, xyh: np.ndarray, valid: np.ndarray, current: int, sdc: int) -> Any:
    """The scene with the given states (steps ``0 .. current + 1``) and ``current_index = current``."""
    steps = xyh.shape[1]
    signals = scenario.signal_state
    if signals is not None:
        rows = np.minimum(np.arange(steps), signals.shape[0] - 1)
        signals = signals[rows]
    return dataclasses.replace(
        scenario, xyh=xyh, valid=valid, current_index=current, sdc=sdc, signal_state=signals
    )
