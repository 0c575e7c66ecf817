"""Seconds a training step takes (forward, backward, AdamW) on real windows, split into its parts.

    python scripts/training_step_time.py --data DIR [--precision auto|float32|bfloat16] [--init shipped]

Times ``TrainingLoss`` of batches of ``--batch-size`` noisy windows of the scenes in DIR with one torch
thread (the first two steps untimed), for the `small` preset from scratch or, with ``--init shipped``, the
shipped model as ``train --init shipped`` trains it (drawing all the tokens it reads). Prints one JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from trajeglish_env import load_pretrained
from trajeglish_env.model import TrajeglishModel, preset
from trajeglish_env.scenario_io import list_scenario_files, load_scenarios
from trajeglish_env.tokenizer.noise import NoiseConfig
from trajeglish_env.tokenizer.vocabulary import load_default_tokenizer
from trajeglish_env.training.dataset import collate_windows, window_config
from trajeglish_env.training.loss import TrainingLoss
from trajeglish_env.training.precision import PRECISIONS, step_autocast, step_dtype
from trajeglish_env.training.train import TrainConfig
from trajeglish_env.training.training_data import TokenizedWindows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a directory of scene shards")
    p.add_argument("--precision", choices=PRECISIONS, default="auto")
    p.add_argument("--init", choices=("none", "shipped"), default="none")
    p.add_argument("--steps", type=int, default=6, help="timed steps")
    p.add_argument("--batch-size", type=int, default=16)
    args = p.parse_args()
    torch.set_num_threads(1)
    scenes = [s for f in list_scenario_files(args.data) for s in load_scenarios(f)]
    if args.init == "shipped":
        shipped = load_pretrained()
        cfg = dataclasses.replace(shipped.config, drawn_size=0, token_bias=True)
        vocabulary = shipped.vocabulary
    else:
        cfg, vocabulary = preset("small", map_select="agents"), load_default_tokenizer()
    torch.manual_seed(0)
    model = TrajeglishModel(cfg)
    loss = TrainingLoss(model, TrainConfig(), vocabulary.templates[:, : cfg.drawn])
    windows = TokenizedWindows(scenes, window_config(cfg), vocabulary, NoiseConfig(0.008, 0.95), 0)
    b = args.batch_size
    batches = [collate_windows([windows[i * b + j] for j in range(b)]) for i in range(args.steps + 2)]
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    cpu = torch.device("cpu")
    parts = {"forward": 0.0, "backward": 0.0, "optimizer": 0.0}
    targets = 0
    for i, batch in enumerate(batches):
        t0 = time.perf_counter()
        with step_autocast(args.precision, cpu, cfg.d_model):
            total, n = loss(batch)
        t1 = time.perf_counter()
        (total / n).backward()
        t2 = time.perf_counter()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        t3 = time.perf_counter()
        if i >= 2:
            parts["forward"] += t1 - t0
            parts["backward"] += t2 - t1
            parts["optimizer"] += t3 - t2
            targets += int(n)
    seconds = {k: round(v / args.steps, 3) for k, v in parts.items()}
    print(
        json.dumps(
            {
                "init": args.init,
                "precision": args.precision,
                "dtype": str(step_dtype(args.precision, cpu, cfg.d_model)).removeprefix("torch."),
                "seconds_a_step": round(sum(seconds.values()), 3),
                **seconds,
                "targets_a_step": targets / args.steps,
                "positions_a_step": b * cfg.max_agents * cfg.steps,
            }
        )
    )


if __name__ == "__main__":
    main()
