"""The AEC env, the README's lead API, timed one timestep a step: on the bundled 24-agent scenes (the
``env`` section's ``aec`` run, issue 16's one-env target) and on the shared WOMD scene (the ``womd``
section). The sdc is the one external agent and replays its log; every other agent is a default
Trajeglish NPC; episodes never end early."""

from __future__ import annotations

import time
from typing import Any

from trajeglish_env.scenario import Scenario

AEC_STEPS, AEC_WARMUP = 70, 5  # the bundled scenes' 80 logged steps after the current one, less a margin
QUICK_AEC_STEPS = 3


def present_agents(scene: Scenario) -> int:
    """Agents valid at the scene's current step: the ones a full-control rollout drives."""
    return int(scene.valid[:, scene.current_index].sum())


def aec_env_speed(scene: Scenario, steps: int, warmup: int) -> dict[str, Any]:
    """Env steps/s of the AEC env on ``scene`` at its default settings (shipped model, default sampling,
    ``torch_threads="auto"``: ``torch_threads`` reports its count at the end), the sdc external and
    replaying its log; episodes never end early. Times ``env.step`` over ``steps`` timesteps after
    ``warmup`` untimed ones (the actions are computed outside the timed region); ``setup_seconds``:
    building the env and its reset."""
    import torch

    from trajeglish_env.benchmark.measure import log_action
    from trajeglish_env.env import RewardConfig, raw_env

    never_end = RewardConfig(
        terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
    )
    start = time.perf_counter()
    env = raw_env([scene], reward=never_end, max_cycles=steps + warmup + 1)
    env.reset(seed=0)
    setup = time.perf_counter() - start
    (ego,) = env.agents  # external="sdc": one AEC agent, so one env.step is one timestep
    elapsed = 0.0
    for k in range(steps + warmup):
        action = log_action(env, ego)
        start = time.perf_counter()
        env.step(action)
        if k >= warmup:
            elapsed += time.perf_counter() - start
        if env.terminations[ego] or env.truncations[ego]:
            raise RuntimeError(
                f"bench aec ({scene.scenario_id}): the ego's episode ended after {k + 1} of "
                f"{steps + warmup} steps"
            )
    rate = steps / elapsed
    agents = present_agents(scene)
    return {
        "api": "aec",
        "ego": "sdc, replaying its log",
        "npc": "trajeglish",
        "agents": agents,
        "torch_threads": env.batch.model_threads or torch.get_num_threads(),  # the env's, in its calls
        "timed_steps": steps,
        "env_steps_per_s": round(rate, 3),
        "agent_steps_per_s": round(rate * agents, 1),
        "setup_seconds": round(setup, 2),
    }


def aec_scenes_speed(agents: int = 24, steps: int = AEC_STEPS, warmup: int = AEC_WARMUP) -> dict[str, Any]:
    """:func:`aec_env_speed` on every bundled scene cut to ``agents`` agents (the sdc and its nearest
    neighbours, as the batched env runs use): ``env_steps_per_s`` over all their timed steps,
    ``agent_steps_per_s`` at ``agents`` agents, and each scene's run (``scenes``). The env's default thread
    setting; the caller's thread count is restored afterwards."""
    import torch

    from trajeglish_env.benchmark.workloads import benchmark_scenes

    threads = torch.get_num_threads()
    try:
        runs = [
            {"scenario_id": s.scenario_id, **aec_env_speed(s, steps, warmup)}
            for s in benchmark_scenes(agents)
        ]
    finally:
        torch.set_num_threads(threads)
    seconds = sum(r["timed_steps"] / r["env_steps_per_s"] for r in runs)
    rate = sum(r["timed_steps"] for r in runs) / seconds
    return {
        "api": "aec",
        "ego": "sdc, replaying its log",
        "npc": "trajeglish",
        "agents": agents,
        "torch_threads": runs[0]["torch_threads"],
        "env_steps_per_s": round(rate, 3),
        "agent_steps_per_s": round(rate * agents, 1),
        "scenes": runs,
    }


def aec_interleaved(rounds: int, highway_steps: int, steps: int, warmup: int) -> dict[str, Any]:
    """The AEC env (:func:`aec_scenes_speed`) and ``intersection-v0`` timed in turn, I, A, I, ..., A, I:
    each AEC run's ratio to the mean of the two ``intersection-v0`` runs beside it, and the median of the
    ``rounds`` ratios. The machine's speed wanders by more within a minute than the AEC env's gap to the
    target (stop 87: a single pair of runs a minute apart gave 0.78x and 1.35x on the same code), so the
    turns put both on the same minutes."""
    import numpy as np

    from trajeglish_env.benchmark.measure import highway_env_speed

    inter = [highway_env_speed(40, highway_steps)["steps_per_s"]]
    aec: list[float] = []
    ratios: list[float] = []
    for _ in range(rounds):
        aec.append(aec_scenes_speed(24, steps, warmup)["env_steps_per_s"])
        inter.append(highway_env_speed(40, highway_steps)["steps_per_s"])
        ratios.append(aec[-1] / ((inter[-1] + inter[-2]) / 2))
    return {
        "rounds": rounds,
        "intersection_steps_per_s": inter,
        "aec_env_steps_per_s": aec,
        "ratios": [round(r, 3) for r in ratios],
        "median_ratio": round(float(np.median(ratios)), 3),
    }
