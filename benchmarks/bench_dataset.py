"""Training-window throughput of WindowDataset (windows per second), single process and DataLoader.

Usage: python benchmarks/bench_dataset.py [--data DIR] [--windows 2000] [--json]
Without --data it generates 32 highway-env scenes once (cached in the temp directory).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report, scene_dir  # noqa: E402
from torch.utils.data import DataLoader  # noqa: E402

from trajeglish_env.dataset import WindowConfig, WindowDataset, collate_windows  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data")
    parser.add_argument("--windows", type=int, default=2000)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    ds = WindowDataset(scene_dir(args.data), WindowConfig(), seed=0)
    n_scenes = len(ds)  # loads the shards
    for i in range(n_scenes):  # warm the per-scene map-chunk cache, as an epoch of training does
        ds[i]
    start = time.perf_counter()
    for i in range(args.windows):
        ds.set_epoch(1 + i // n_scenes)
        ds[i % n_scenes]
    single = args.windows / (time.perf_counter() - start)

    loader = DataLoader(
        ds,
        batch_size=args.batch,
        num_workers=args.workers,
        collate_fn=collate_windows,
        persistent_workers=True,
        shuffle=True,
    )
    epochs = max(1, args.windows // n_scenes)
    next(iter(loader))  # start the workers
    start = time.perf_counter()
    count = 0
    for _ in range(epochs):
        for batch in loader:
            count += batch["agent_xyh"].shape[0]
    loader_rate = count / (time.perf_counter() - start)
    report(
        {
            "scenes": n_scenes,
            "windows_per_second_single_process": round(single, 1),
            f"windows_per_second_dataloader_{args.workers}_workers": round(loader_rate, 1),
            "window": "24 agents x 33 steps, 96 map chunks x 20 points",
        },
        args.json,
    )


if __name__ == "__main__":
    main()
