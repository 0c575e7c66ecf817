"""Closed-loop rollout speed: simulated agent-steps per second of the shipped model (full control).

Scenes: a bundled 24-agent SUMO scene (or the largest bundled scene) and a synthetic 200-agent grid
scene (sliding window in space: ceil(200/16) model contexts per timestep and more). ``--rollouts``
rollouts are sampled in one batch.

Usage: python benchmarks/bench_rollout.py [--rollouts 8] [--horizon 40] [--threads 1] [--json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.benchmark.measure import rollout_speed  # noqa: E402
from trajeglish_env.benchmark.workloads import grid_scene  # noqa: E402
from trajeglish_env.checkpoint import load_pretrained  # noqa: E402
from trajeglish_env.env.scenes import load_bundle  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=40)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    ckpt = load_pretrained()
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]
    count = [int(s.valid[:, s.current_index].sum()) for s in scenes]
    small = scenes[int(np.argmin(np.abs(np.array(count) - 24)))]
    result = {
        "model": "shipped small",
        "rollouts": args.rollouts,
        "horizon": args.horizon,
        "threads": args.threads,
    }
    result["scene_small"] = rollout_speed(ckpt, small, args.rollouts, args.horizon)
    result["scene_200"] = rollout_speed(ckpt, grid_scene(200), args.rollouts, args.horizon)
    report(result, args.json)


if __name__ == "__main__":
    main()
