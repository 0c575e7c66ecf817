"""Model throughput: training tokens/s, and decoding tokens/s with and without the key/value cache.

Decoding is measured on a 24-agent x 32-step sequence (768 tokens). Without the cache every new token
needs a full forward pass over the sequence so far; its cost per token is measured at 32 evenly spaced
positions (a full 768-pass run takes minutes) and the speed-up is the ratio of the mean per-token times.

Usage: python benchmarks/bench_model.py [--preset small] [--threads 2] [--json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.model import SceneInputs, TrajeglishModel, preset  # noqa: E402
from trajeglish_env.sampling import START  # noqa: E402


def random_inputs(cfg, batch: int, seed: int = 0) -> tuple[SceneInputs, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a, m, p = cfg.max_agents, cfg.max_polylines, cfg.points_per_polyline
    scene = SceneInputs(
        agent_xyh=torch.randn(batch, a, 3, generator=g) * 20,
        agent_size=torch.rand(batch, a, 2, generator=g) * 3 + 1,
        agent_kind=torch.randint(0, 3, (batch, a), generator=g),
        agent_mask=torch.ones(batch, a, dtype=torch.bool),
        map_points=torch.randn(batch, m, p, 2, generator=g) * 40,
        map_point_mask=torch.ones(batch, m, p, dtype=torch.bool),
        map_kind=torch.randint(0, 20, (batch, m), generator=g),
        map_mask=torch.ones(batch, m, dtype=torch.bool),
    )
    return scene, torch.randint(0, cfg.vocab_size, (batch, a, cfg.steps), generator=g)


def training_speed(name: str, batch: int, steps: int) -> float:
    cfg = preset(name)
    model = TrajeglishModel(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    scene, tokens = random_inputs(cfg, batch)
    loss, _ = model.loss(scene, tokens, tokens)  # warm-up
    loss.backward()
    start = time.perf_counter()
    for _ in range(steps):
        loss, n = model.loss(scene, tokens, tokens)
        loss.backward()
        opt.step()
        opt.zero_grad()
    return steps * n / (time.perf_counter() - start)


@torch.no_grad()
def decoding_speed(name: str, probes: int = 32) -> dict[str, float]:
    cfg = preset(name, max_agents=24, steps=32)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_inputs(cfg, 1)
    a, length = cfg.max_agents, cfg.max_agents * cfg.steps
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(1, -1)
    start = time.perf_counter()
    cache, agents = model.start_decoding(scene)
    for p in range(length):
        carried = torch.full((1, 1), START) if p == 0 else ids[:, p - 1 : p]
        own = torch.full((1, 1), -1) if p < a else ids[:, p - a : p - a + 1]
        model.decode(cache, agents, scene.agent_kind[:, [p % a]], carried, own)
    cached = length / (time.perf_counter() - start)
    positions = torch.linspace(0, length - 1, probes).long().tolist()
    start = time.perf_counter()
    for p in positions:
        t = p // a + 1  # the sequence up to and including the timestep of position p
        model(scene, tokens[:, :, :t])
    uncached = len(positions) / (time.perf_counter() - start)
    return {
        "decode_tokens_per_s_cached": round(cached, 1),
        "decode_tokens_per_s_uncached": round(uncached, 2),
        "cache_speedup": round(cached / uncached, 1),
    }


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
