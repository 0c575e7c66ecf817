"""Play AEC episodes with a policy per external agent, and summarise them (collision and off-road rates,
progress, returns)."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from policies.base import Policy

PolicyMap = Mapping[str, Policy] | Policy | Callable[[str], Policy]


@dataclass(frozen=True)
class EpisodeResult:
    """One episode: per external agent its return, whether it collided / went off-road / reached its goal
    at any step of the episode, its progress (m, fraction), and whether its route has a goal at all (an
    agent parked in the log has none)."""

    scenario_id: str
    steps: int
    returns: dict[str, float]
    collision: dict[str, bool]
    offroad: dict[str, bool]
    goal: dict[str, bool]
    progress_m: dict[str, float]
    route_fraction: dict[str, float]
    video: str | None = field(default=None)  # the video's path (a string: the result writes as JSON)
    has_goal: dict[str, bool] = field(default_factory=dict)


POLICY_FORMS = (
    "a Policy object (with reset(env, agent) and act(env, agent, observation)), a mapping agent -> Policy, "
    "or a factory agent -> Policy"
)


def check_policy(policy: Any, agent: str, source: str) -> Policy:
    """``policy`` if it is a Policy *object*; else a TypeError saying what it is and what was expected."""
    if isinstance(policy, type):
        raise TypeError(
            f"{source} for agent {agent!r} is the class {policy.__name__}, not an object of it: "
            f"pass {policy.__name__}()"
        )
    missing = [m for m in ("reset", "act") if not callable(getattr(policy, m, None))]
    if missing:
        raise TypeError(
            f"{source} for agent {agent!r} ({type(policy).__name__}) has no {' and no '.join(missing)} "
            f"method; expected {POLICY_FORMS} (wrap a function observation -> action as FunctionPolicy(fn))"
        )
    return policy


def policy_for(policies: PolicyMap, agent: str) -> Policy:
    """The policy of ``agent``: a mapping entry, the single policy, or the factory's result."""
    if isinstance(policies, Mapping):
        if agent not in policies:
            raise KeyError(f"no policy for agent {agent!r}; policies are given for {sorted(policies)}")
        return check_policy(policies[agent], agent, "the mapping's policy")
    if isinstance(policies, Policy) and not isinstance(policies, type):
        return policies
    if callable(policies) and not isinstance(policies, type):
        name = getattr(policies, "__name__", type(policies).__name__)
        try:
            made = policies(agent)
        except Exception as exc:  # a function observation -> action, fed the agent's name
            raise TypeError(
                f"policies: {name} was called with the agent name {agent!r} (as a factory agent -> Policy) "
                f"and raised {type(exc).__name__}: {exc}; a function observation -> action is not a policy; "
                f"expected {POLICY_FORMS}, e.g. FunctionPolicy(my_function)"
            ) from exc
        if isinstance(made, np.ndarray) or np.isscalar(made) or made is None:
            raise TypeError(
                f"policies: {name} was called with the "
                f"agent name {agent!r} and returned {type(made).__name__}, not a Policy: a function "
                f"observation -> action is not a policy; expected {POLICY_FORMS}, e.g. "
                "FunctionPolicy(my_function)"
            )
        return check_policy(made, agent, "the factory's policy")
    return check_policy(policies, agent, "policies")


def aec_of(env: Any) -> Any:
    """The AEC env to play: ``env`` itself, or the one inside a (wrapped) ``EgoEnv``; anything else is a
    TypeError saying what is expected."""
    if hasattr(env, "agent_iter"):
        return env
    inner = getattr(getattr(env, "unwrapped", None), "aec", None)
    if inner is None or not hasattr(inner, "agent_iter"):
        raise TypeError(
            f"play_episode / evaluate play a PettingZoo AEC env (trajeglish_env.env(...)) or an EgoEnv "
            f"(gymnasium.make('trajeglish_env/Ego-v0')), got {type(env).__name__}"
        )
    return inner


def play_episode(
    env: Any,
    policies: PolicyMap,
    seed: int | None = None,
    options: dict[str, Any] | None = None,
    video: str | os.PathLike[str] | None = None,
) -> EpisodeResult:
    """Reset ``env`` and play one AEC episode to the end; optionally write its video (GIF/MP4: the path is
    checked before the episode plays). ``env``: an AEC env, or a Gymnasium ``EgoEnv`` (made or wrapped: its
    AEC env is played, the policies driving its ego)."""
    env = aec_of(env)
    if video is not None:
        from trajeglish_env.render import check_output

        check_output(video, (".gif", ".mp4"))
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
        collision={a: bool(i.get("collision_steps", 0) > 0 or i.get("collision")) for a, i in infos.items()},
        offroad={a: bool(i.get("offroad_steps", 0) > 0 or i.get("offroad")) for a, i in infos.items()},
        goal={a: bool(i.get("goal_reached") or i.get("goal")) for a, i in infos.items()},
        progress_m={a: float(i.get("progress_m", 0.0)) for a, i in infos.items()},
        route_fraction={a: float(i.get("route_fraction", 0.0)) for a, i in infos.items()},
        video=None if path is None else str(path),
        has_goal={a: bool(i.get("has_goal", True)) for a, i in infos.items()},
    )


def summarize(results: list[EpisodeResult]) -> dict[str, float | None]:
    """Rates and means over every (episode, external agent) pair; the goal rate and route fraction over
    the pairs whose route has a goal (a parked agent's counted as a failure: replaying the shared WOMD
    scene's log read a goal rate of 0.40), ``agents_with_goal`` of them (None where no agent has a goal:
    the result writes as strict JSON)."""

    def values(name: str, goal_only: bool = False) -> np.ndarray:
        return np.array(
            [
                v
                for r in results
                for a, v in getattr(r, name).items()
                if not goal_only or r.has_goal.get(a, True)
            ],
            dtype=np.float64,
        )

    def mean(x: np.ndarray) -> float | None:
        return float(x.mean()) if len(x) else None

    if not results:
        raise ValueError("summarize: no episodes")
    return {
        "episodes": float(len(results)),
        "agents": float(len(values("returns"))),
        "collision_rate": float(values("collision").mean()),
        "offroad_rate": float(values("offroad").mean()),
        "agents_with_goal": float(len(values("goal", goal_only=True))),
        "goal_rate": mean(values("goal", goal_only=True)),
        "mean_progress_m": float(values("progress_m").mean()),
        "mean_route_fraction": mean(values("route_fraction", goal_only=True)),
        "mean_return": float(values("returns").mean()),
        "mean_steps": float(np.mean([r.steps for r in results])),
    }


def evaluate(
    env: Any, policies: PolicyMap, episodes: int, seed: int = 0, scenes: list[Any] | None = None
) -> dict[str, float | None]:
    """Play ``episodes`` episodes (seeds ``seed, seed + 1, ...``; scene ``scenes[k % len(scenes)]`` when
    given, else the env's choice) and summarise them."""
    results = []
    for k in range(episodes):
        options = {"scene": scenes[k % len(scenes)]} if scenes else None
        results.append(play_episode(env, policies, seed=seed + k, options=options))
    return summarize(results)
