"""Play AEC episodes with a policy per external agent, and summarise them (collision and off-road rates,
progress, returns)."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policies.base import Policy

PolicyMap = Mapping[str, Policy] | Policy | Callable[[str], Policy]


@dataclass(frozen=True)
class EpisodeResult:
    """One episode: per external agent its return, collision, off-road, goal and progress (m, fraction)."""

    scenario_id: str
    steps: int
    returns: dict[str, float]
    collision: dict[str, bool]
    offroad: dict[str, bool]
    goal: dict[str, bool]
    progress_m: dict[str, float]
    route_fraction: dict[str, float]
    video: Path | None = field(default=None)


def policy_for(policies: PolicyMap, agent: str) -> Policy:
    """The policy of ``agent``: a mapping entry, the single policy, or the factory's result."""
    if isinstance(policies, Mapping):
        if agent not in policies:
            raise KeyError(f"no policy for agent {agent!r}; policies are given for {sorted(policies)}")
        return policies[agent]
    if isinstance(policies, Policy):
        return policies
    if callable(policies):
        return policies(agent)
    raise TypeError(f"policies: expected a mapping, a Policy or a factory, got {type(policies).__name__}")


def play_episode(
    env: Any,
    policies: PolicyMap,
    seed: int | None = None,
    options: dict[str, Any] | None = None,
    video: str | os.PathLike[str] | None = None,
) -> EpisodeResult:
    """Reset ``env`` and play one AEC episode to the end; optionally write its video (GIF/MP4)."""
    env.reset(seed=seed, options=options)
    raw = env.unwrapped
    chosen: dict[str, Policy] = {}
    for agent in list(env.agents):
        chosen[agent] = policy_for(policies, agent)
        chosen[agent].reset(env, agent)
    returns = dict.fromkeys(env.agents, 0.0)
    infos: dict[str, dict[str, Any]] = {}
    steps = 0
    for agent in env.agent_iter():
        obs, reward, terminated, truncated, info = env.last()
        returns[agent] += float(reward)
        if terminated or truncated:
            infos[agent] = dict(info)
            env.step(None)
            continue
        env.step(chosen[agent].act(env, agent, obs))
        steps = max(steps, raw.sim.steps)
    path = raw.save_video(video) if video is not None else None
    return EpisodeResult(
        scenario_id=raw.scenario.scenario_id,
        steps=raw.sim.steps,
        returns=returns,
        collision={a: bool(i.get("collision", False)) for a, i in infos.items()},
        offroad={a: bool(i.get("offroad", False)) for a, i in infos.items()},
        goal={a: bool(i.get("goal", False)) for a, i in infos.items()},
        progress_m={a: float(i.get("progress_m", 0.0)) for a, i in infos.items()},
        route_fraction={a: float(i.get("route_fraction", 0.0)) for a, i in infos.items()},
        video=path,
    )


def summarize(results: list[EpisodeResult]) -> dict[str, float]:
    """Rates and means over every (episode, external agent) pair."""

    def values(name: str) -> np.ndarray:
        return np.array([v for r in results for v in getattr(r, name).values()], dtype=np.float64)

    if not results:
        raise ValueError("summarize: no episodes")
    return {
        "episodes": float(len(results)),
        "agents": float(len(values("returns"))),
        "collision_rate": float(values("collision").mean()),
        "offroad_rate": float(values("offroad").mean()),
        "goal_rate": float(values("goal").mean()),
        "mean_progress_m": float(values("progress_m").mean()),
        "mean_route_fraction": float(values("route_fraction").mean()),
        "mean_return": float(values("returns").mean()),
        "mean_steps": float(np.mean([r.steps for r in results])),
    }


def evaluate(
    env: Any, policies: PolicyMap, episodes: int, seed: int = 0, scenes: list[Any] | None = None
) -> dict[str, float]:
    """Play ``episodes`` episodes (seeds ``seed, seed + 1, ...``; scene ``scenes[k % len(scenes)]`` when
    given, else the env's choice) and summarise them."""
    results = []
    for k in range(episodes):
        options = {"scene": scenes[k % len(scenes)]} if scenes else None
        results.append(play_episode(env, policies, seed=seed + k, options=options))
    return summarize(results)
