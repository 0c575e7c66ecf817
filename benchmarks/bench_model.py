"""Model throughput: training tokens/s, and decoding tokens/s with and without the key/value cache.

Decoding is measured on a 24-agent x 32-step sequence (768 tokens). Without the cache every new token
needs a full forward pass over the sequence so far; its cost per token is measured at 32 evenly spaced
positions (a full 768-pass run takes minutes) and the speed-up is the ratio of the mean per-token times.

Usage: python benchmarks/bench_model.py [--preset small] [--threads 2] [--json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.benchmark.measure import decoding_speed, training_speed  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--preset", default="small")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    result = {"preset": args.preset, "threads": args.threads, "device": "cpu"}
    result["train_tokens_per_s"] = round(training_speed(args.preset, args.batch, args.steps), 1)
    result.update(decoding_speed(args.preset))
    report(result, args.json)


if __name__ == "__main__":
    main()
