"""Closed-loop rollout speed: simulated agent-steps per second of the shipped model (full control).

Scenes: a bundled 24-agent SUMO scene (or the largest bundled scene) and a synthetic 200-agent grid
scene (sliding window in space: ceil(200/16) model contexts per timestep and more). ``--rollouts``
rollouts are sampled in one batch.

Usage: python benchmarks/bench_rollout.py [--rollouts 8] [--horizon 40] [--threads 1] [--json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.checkpoint import load_pretrained  # noqa: E402
from trajeglish_env.sampler import SamplingConfig, rollout  # noqa: E402
from trajeglish_env.scenario import AgentKind, Scenario  # noqa: E402
from trajeglish_env.scenario_io import load_scenarios  # noqa: E402


def grid_scene(n: int = 200, steps: int = 91) -> Scenario:
    """``n`` vehicles on parallel lanes 8 m apart, driving +x at 5-10 m/s."""
    rng = np.random.default_rng(0)
    cols = 20
    start = np.stack([np.arange(n) % cols * 12.0, np.arange(n) // cols * 4.0], -1)
    speed = rng.uniform(5, 10, n)
    xyh = np.zeros((n, steps, 3))
    xyh[..., 0] = start[:, :1] + speed[:, None] * np.arange(steps) * 0.1
    xyh[..., 1] = start[:, 1:]
    lanes = [np.stack([np.arange(-50, 400.0), np.full(450, y)], -1) for y in np.unique(start[:, 1])]
    return Scenario.from_arrays(
        xyh,
        np.ones((n, steps), bool),
        np.tile([4.5, 1.9], (n, 1)),
        np.full(n, AgentKind.VEHICLE),
        sdc=0,
        polylines=lanes,
        polyline_kinds=[2] * len(lanes),
        scenario_id=f"grid-{n}",
        source="bench",
    )


def measure(ckpt, scene: Scenario, rollouts: int, horizon: int) -> dict[str, float]:
    agents = int(scene.valid[:, scene.current_index].sum())
    start = time.perf_counter()
    rollout(ckpt, scene, rollouts, horizon, config=SamplingConfig(seed=0))
    seconds = time.perf_counter() - start
    return {
        "agents": agents,
        "seconds": round(seconds, 2),
        "agent_steps_per_s": round(agents * horizon * rollouts / seconds, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=40)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    ckpt = load_pretrained()
    bundle = load_scenarios(
        Path(sys.modules["trajeglish_env"].__file__).parent / "assets" / "scenes_bundle.scn.npz"
    )
    count = [int(s.valid[:, s.current_index].sum()) for s in bundle]
    small = bundle[int(np.argmin(np.abs(np.array(count) - 24)))]
    result = {
        "model": "shipped small",
        "rollouts": args.rollouts,
        "horizon": args.horizon,
        "threads": args.threads,
    }
    result["scene_small"] = measure(ckpt, small, args.rollouts, args.horizon)
    result["scene_200"] = measure(ckpt, grid_scene(200), args.rollouts, args.horizon)
    report(result, args.json)


if __name__ == "__main__":
    main()
