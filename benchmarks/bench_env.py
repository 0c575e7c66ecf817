"""Environment stepping speed: 1 external ego + 23 Trajeglish NPCs, the same scene with replay and IDM NPCs,
and, in the same run, highway-env's own intersection env with a similar number of IDM vehicles.

Usage: python benchmarks/bench_env.py [--steps 40] [--baseline-steps 300] [--json]

Scene: the bundled SUMO scene with the most agents, cut to the sdc and the 23 agents nearest to it at the
current step. Model: the shipped checkpoint if present, else the ``small`` preset with random weights
(same architecture and cost; reported as ``model``). The ego replays its log through continuous actions;
episodes never end early (terminations off). Both envs step at 10 Hz (highway-env configured with
simulation_frequency = policy_frequency = 10, one IDM step per env step, no rendering; it removes
vehicles that have crossed, so it starts with 40 to keep about 20 on the road). One torch thread.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.env import RewardConfig, TrajeglishNPC, raw_env  # noqa: E402
from trajeglish_env.env.scenes import load_bundle  # noqa: E402
from trajeglish_env.scenario import Scenario  # noqa: E402

NEVER_END = RewardConfig(terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False)


def benchmark_scene(agents: int = 24) -> Scenario:
    """The sdc and its ``agents - 1`` nearest present agents from the busiest bundled scene."""
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]
    sc = max(scenes, key=lambda s: int(s.valid[:, s.current_index].sum()))
    cur = sc.current_index
    present = np.flatnonzero(sc.valid[:, cur])
    dist = np.linalg.norm(sc.xyh[present, cur, :2] - sc.xyh[sc.sdc, cur, :2], axis=-1)
    keep = np.sort(present[np.argsort(dist, kind="stable")[:agents]])
    return sc.with_agents(keep)


def model_checkpoint() -> tuple[Any, str]:
    """The shipped model, or the ``small`` preset with random weights when it is not installed."""
    import torch

    from trajeglish_env.checkpoint import Checkpoint, CheckpointError, load_pretrained
    from trajeglish_env.model import TrajeglishModel, preset
    from trajeglish_env.tokenizer import load_default_tokenizer

    try:
        return load_pretrained(), "shipped"
    except CheckpointError:
        vocab = load_default_tokenizer()
        torch.manual_seed(0)
        model = TrajeglishModel(preset("small", vocab_size=vocab.size)).eval()
        return Checkpoint(model=model, vocabulary=vocab, training={}), "small preset, random weights"


def time_env(scene: Scenario, npc: Any, steps: int, warmup: int = 2) -> float:
    """Env steps per second (one step = every agent moves 0.1 s) with a log-replaying ego."""
    env = raw_env([scene], npc=npc, reward=NEVER_END, max_cycles=steps + warmup)
    env.reset(seed=0)
    agent = env.agent_selection
    i = env.agent_index(agent)
    start = 0.0
    for k in range(steps + warmup):
        if k == warmup:
            start = time.perf_counter()
        target = scene.xyh[i, min(env.sim.t + 1, scene.num_steps - 1)]
        env.step(env.action_towards(agent, target))
    return steps / (time.perf_counter() - start)


def time_highway_env(vehicles: int, steps: int) -> tuple[float, float]:
    """highway-env intersection steps per second at 10 Hz, and the mean number of vehicles on the road."""
    from highway_env.envs.intersection_env import IntersectionEnv

    config = {
        "simulation_frequency": 10,
        "policy_frequency": 10,
        "initial_vehicle_count": vehicles,
        "spawn_probability": 0.6,
        "duration": 10_000,
        "offroad_terminal": False,
    }
    env = IntersectionEnv(config=config)
    env.reset(seed=0)
    counts, start, episodes = [], time.perf_counter(), 0
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(1)  # IDLE: the ego keeps its lane and speed
        counts.append(len(env.road.vehicles))
        if terminated or truncated:
            episodes += 1
            env.reset(seed=episodes)
    return steps / (time.perf_counter() - start), float(np.mean(counts))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=40, help="timed steps with Trajeglish NPCs")
    parser.add_argument("--rule-steps", type=int, default=300, help="timed steps with replay / IDM NPCs")
    parser.add_argument("--baseline-steps", type=int, default=300, help="timed highway-env steps")
    parser.add_argument(
        "--baseline-vehicles",
        type=int,
        default=40,
        help="highway-env initial_vehicle_count (it clears arrived vehicles: 40 keeps about 20 on the road)",
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    scene = benchmark_scene()
    ckpt, model = model_checkpoint()
    trajeglish = time_env(scene, TrajeglishNPC(ckpt), args.steps)
    replay = time_env(scene, "replay", args.rule_steps)
    idm = time_env(scene, "idm", args.rule_steps)
    baseline, vehicles = time_highway_env(args.baseline_vehicles, args.baseline_steps)
    report(
        {
            "scene": scene.scenario_id,
            "agents": scene.num_agents,
            "model": model,
            "model_max_agents": ckpt.config.max_agents,
            "trajeglish_npcs_steps_per_s": round(trajeglish, 2),
            "replay_npcs_steps_per_s": round(replay, 1),
            "idm_npcs_steps_per_s": round(idm, 1),
            "highway_env_intersection_steps_per_s": round(baseline, 1),
            "highway_env_mean_vehicles": round(vehicles, 1),
            "ratio_trajeglish_to_highway_env": round(trajeglish / baseline, 4),
            "ratio_replay_to_highway_env": round(replay / baseline, 3),
        },
        args.json,
    )


if __name__ == "__main__":
    main()
