"""Does the model follow the road by itself? Each scene's sdc alone on its map (every other agent removed,
``Scenario.with_agents``), ``--rollouts`` unguarded rollouts of 8 s: the share of rollouts in which the
vehicle gets farther than ``--distance`` metres from every lane centre, by scene kind. Traffic plays no part,
so a vehicle that leaves the road here does not read it (docs/evaluation.md, "The road in the agent's own
frame": the shipped model leaves every development racetrack).

    python scripts/lone_vehicle_probe.py --data DIR [--ckpt FILE] [--rollouts 8] [--temperature T] [--json]
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np
import torch
from tqdm import tqdm

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE, SamplingConfig
from trajeglish_env.sampler.rollouts import rollout
from trajeglish_env.scenario import LANE_KINDS, Scenario
from trajeglish_env.training.dataset import SceneStore


def lane_distance(scene: Scenario, xy: np.ndarray) -> np.ndarray:
    """Distance ``[n]`` of points ``xy [n,2]`` to the nearest lane-centre segment of ``scene`` (inf: none)."""
    segments = [
        np.stack([p[:-1], p[1:]], axis=1)
        for k in range(scene.num_polylines)
        if scene.map_kind[k] in LANE_KINDS and len(p := scene.polyline(k)) > 1
    ]
    if not segments:
        return np.full(len(xy), np.inf)
    seg = np.concatenate(segments)  # [S,2,2]
    a, d = seg[:, 0], seg[:, 1] - seg[:, 0]
    t = np.clip(((xy[:, None] - a[None]) * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(xy[:, None] - (a[None] + t[..., None] * d[None]), axis=-1).min(-1)


def scene_kind(sc: Scenario) -> str:
    """The kind of a generated scene from its id (``SOURCE-KIND-SEED[-INDEX]``: ``highway-two-way-123`` is
    ``two-way``, ``sumo-grid-50050-1`` ``grid``), else its source."""
    parts = sc.scenario_id.split("-")
    kind = parts[1:]
    while kind and kind[-1].isdigit():
        kind.pop()
    seeded = len(kind) < len(parts) - 1  # at least one number after the kind
    return "-".join(kind) if kind and seeded else sc.source


def probe(
    scenes: list[Scenario],
    ckpt: object,
    rollouts: int,
    distance: float,
    seed: int,
    temperature: float = DEFAULT_TEMPERATURE,
) -> dict:
    """Counts per scene kind (the second part of the scene id, or the source) and overall."""
    off: collections.Counter[str] = collections.Counter()
    total: collections.Counter[str] = collections.Counter()
    for sc in tqdm(scenes, desc="lone vehicles", leave=False):
        kind = scene_kind(sc)
        one = sc.with_agents(np.array([sc.sdc]))
        r = rollout(
            ckpt, one, rollouts, 80, config=SamplingConfig(guard=False, seed=seed, temperature=temperature)
        )
        future = r.xyh[:, 0, r.future, :2]  # [R,H,2]
        far = lane_distance(sc, future.reshape(-1, 2)).reshape(future.shape[:2]) > distance
        off[kind] += int(far.any(1).sum())
        total[kind] += rollouts
    n = sum(total.values())
    return {
        "scenes": len(scenes),
        "rollouts": n,
        "off_road": sum(off.values()),
        "rate": sum(off.values()) / max(n, 1),
        "by_kind": {k: {"off_road": off[k], "rollouts": total[k]} for k in sorted(total)},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="scenario directory or file (*.scn.npz)")
    ap.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--scenes", type=int, help="the first N scenes only")
    ap.add_argument("--distance", type=float, default=2.5, help="metres from every lane centre: off the road")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--temperature", type=float, default=0.75, help="sampling temperature (the env's default)"
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.rollouts < 1 or args.distance <= 0 or args.temperature <= 0:
        ap.error(
            f"--rollouts must be >= 1, --distance and --temperature > 0, got {args.rollouts}, "
            f"{args.distance} and {args.temperature}"
        )
    torch.set_num_threads(1)
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    scenes = SceneStore(args.data).scenes[: args.scenes]
    result = probe(scenes, ckpt, args.rollouts, args.distance, args.seed, args.temperature)
    if args.json:
        print(json.dumps(result))
        return
    for kind, c in result["by_kind"].items():
        print(f"{kind}: {c['off_road']} / {c['rollouts']} off the road")
    print(f"all: {result['off_road']} / {result['rollouts']} = {result['rate']:.3f}")


if __name__ == "__main__":
    main()
