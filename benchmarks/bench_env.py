"""Batched environment speed: B = 1, 8, 32, 128, 256 scenes of 24 agents (1 external ego + 23 NPCs each),
Trajeglish and replay NPCs, each run in its own process (peak memory), beside highway-env's own
intersection env with a similar number of IDM vehicles measured in the same run (before and after); prints
the ratios.

Usage: python benchmarks/bench_env.py [--batches 1 8 32 128 256] [--steps N] [--threads auto] [--json]

This is ``trajeglish bench --sections env`` (see trajeglish_env/benchmark/measure.py:env_speed for the
exact workload: the bundled SUMO scenes cut to the sdc and its 23 nearest agents, the ego replaying its
log through continuous actions, episodes that never end early, env.step timed alone).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.benchmark.suite import BenchConfig, run_suite, summary_lines  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32, 128, 256])
    parser.add_argument(
        "--steps", type=int, default=None, help="timed steps per Trajeglish run (default: one window cycle)"
    )
    parser.add_argument("--threads", default="auto")
    parser.add_argument("--cache-dtype", choices=("bfloat16", "float32"), default="bfloat16")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    threads = args.threads if args.threads == "auto" else int(args.threads)
    config = BenchConfig(
        batches=tuple(args.batches),
        env_steps=args.steps,
        torch_threads=threads,
        cache_dtype=args.cache_dtype,
        sections=("env",),
    )
    result = run_suite(config)
    if args.json:
        report(result, True)
    else:
        print("\n".join(summary_lines(result)))


if __name__ == "__main__":
    main()
