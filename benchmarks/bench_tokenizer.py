"""Throughput of motion tokenization (exact argmin over V templates with corner distances), in agent-steps/s.

Usage: python benchmarks/bench_tokenizer.py [--agents 20000] [--steps 51] [--threads 1 2] [--data DIR]
       [--json]

Uses the shipped V=384 vocabulary. Without ``--data`` it tokenizes synthetic smooth trajectories of all
three classes; with ``--data`` the scenes of a scenario directory (repeated to reach ``--agents`` rows).
Each setting is run ``--repeats`` times and the best wall time is reported (the machine may be shared).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.benchmark.measure import machine, tokenizer_speed  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=20000)
    parser.add_argument("--steps", type=int, default=51)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--noise-agents", type=int, default=2000, help="agents for the noisy-tokenization figure"
    )
    parser.add_argument("--data", default=None)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    result = machine() | tokenizer_speed(
        args.agents, args.steps, args.threads, args.repeats, args.noise_agents, args.data
    )
    report(result, args.json)


if __name__ == "__main__":
    main()
