"""Training-window throughput of WindowDataset (windows per second), single process and DataLoader.

Usage: python benchmarks/bench_dataset.py [--data DIR] [--windows 2000] [--json]
Without --data it generates 32 highway-env scenes once (cached in the temp directory).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report, scene_dir  # noqa: E402

from trajeglish_env.benchmark.measure import dataset_speed, machine  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data")
    parser.add_argument("--windows", type=int, default=2000)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    result = machine() | dataset_speed(scene_dir(args.data), args.windows, args.batch, args.workers)
    result["window"] = "24 agents x 33 steps, 96 map chunks x 20 points"
    report(result, args.json)


if __name__ == "__main__":
    main()
