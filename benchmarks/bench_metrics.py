"""Time of scoring rollouts with the realism metrics (WOSAC 2025 config) on a synthetic scene.

Usage: python benchmarks/bench_metrics.py [--agents 128] [--rollouts 32] [--evaluated 8 0] [--repeats 3]
       [--json]

The scene is built with NumPy: a 4-lane ring road (radius 250 m, surface-street lanes, road edges and
lane centres sampled every 0.5 m like the generated highway maps, about 6,400 road-edge segments), a
signal-controlled lane with a red light, and ``--agents`` vehicles driving 91 steps at 10 Hz, all of
them simulated. ``--evaluated`` lists the numbers of scored agents to time: 8 is the WOSAC / WOMD
setting (the sdc and the agents to predict; our generated scenes name up to 8 too), 0 means every
agent (a scene that names no agents of interest). The rollouts are the logged future plus random-walk
noise (so some leave the road and some collide). The best wall time of ``--repeats`` runs is reported
with its CPU time; the machine may be shared.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.benchmark.measure import machine, metrics_time  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=128)
    parser.add_argument("--rollouts", type=int, default=32)
    parser.add_argument("--evaluated", type=int, nargs="+", default=[8, 0], help="scored agents (0: all)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", default="2025")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    result = machine() | metrics_time(args.agents, args.rollouts, args.evaluated, args.repeats, args.config)
    report(result, args.json)


if __name__ == "__main__":
    main()
