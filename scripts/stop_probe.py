"""Reactivity probe on logged stops: in ``+stop`` scenes (``trajeglish generate --kinds highway+stop,...``)
the stop event's vehicle replays its log (it brakes hard to a stop and holds) while the model drives every
other agent; the share of rollouts in which a model-driven agent's box runs into it. The log has none
(scenes with a crash are not kept), so any hit is the model's.

    python scripts/stop_probe.py --data DIR [--ckpt FILE] [--rollouts 4] [--guard] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from tqdm import tqdm

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.rollouts import rollout
from trajeglish_env.sources.highway_stops import stop_event_in
from trajeglish_env.training.dataset import SceneStore


def hits_stopper(
    xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, stopper: int, first: int
) -> np.ndarray:
    """``[R]`` whether any other agent's box overlaps the stopper's at some step from ``first`` on
    (``xyh [R,N,T,3]``, ``valid [R,N,T]``)."""
    hit = np.zeros(xyh.shape[0], dtype=bool)
    others = np.arange(xyh.shape[1]) != stopper
    for r in range(xyh.shape[0]):
        for t in range(first, xyh.shape[2]):
            idx = np.flatnonzero(valid[r, :, t] & others)
            if box_collisions(xyh[r, stopper, t], size[stopper], xyh[r, idx, t], size[idx]).any():
                hit[r] = True
                break
    return hit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", required=True, help="directories of +stop scenes")
    parser.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--guard", action="store_true", help="guarded sampling (default: the model alone)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    config = SamplingConfig(guard=args.guard)
    scenes = SceneStore(args.data).scenes
    events = [(s, stop_event_in(s)) for s in scenes]
    # stops that begin after the current step, so the model sees the whole stop
    events = [(s, e) for s, e in events if e is not None and e[1] > s.current_index]
    if not events:
        raise SystemExit(f"stop_probe: no +stop scene with its event after the current step in {args.data}")
    hits = []
    for scene, (stopper, _) in tqdm(events, desc="stop probe"):
        controlled = scene.valid[:, scene.current_index].copy()
        controlled[stopper] = False
        r = rollout(ckpt, scene, rollouts=args.rollouts, controlled=controlled, config=config)
        hits.append(hits_stopper(r.xyh, r.valid, scene.size, stopper, scene.current_index + 1))
    hit = np.concatenate(hits)
    result = {
        "scenes": len(events),
        "rollouts": int(hit.size),
        "hits": int(hit.sum()),
        "rate": float(hit.mean()),
    }
    print(
        json.dumps(result)
        if args.json
        else f"{result['hits']} of {result['rollouts']} rollouts hit the stopper: {result['rate']:.3f}"
    )


if __name__ == "__main__":
    main()
