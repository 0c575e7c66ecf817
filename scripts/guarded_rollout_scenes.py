"""Guarded rollouts of a model as scene shards: each scene's simulated agents (those valid at its current
step) get the future of one guarded rollout instead of the log's. Data for fine-tuning a model on its own
guarded behaviour (the distillation experiment of docs/evaluation.md):

    python scripts/guarded_rollout_scenes.py --data out/train_hw --out out/guarded_hw --rollouts 2
    trajeglish train --data out/train_hw out/guarded_hw --init shipped --lr 1e-4 --steps 600 --out runs/d
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE, SamplingConfig
from trajeglish_env.sampler.rollouts import rollout
from trajeglish_env.scenario import Scenario
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.dataset import SceneStore

SCENES_PER_SHARD = 16


def guarded_scenes(
    ckpt: object, scene: Scenario, rollouts: int, seed: int, temperature: float = DEFAULT_TEMPERATURE
) -> list[Scenario]:
    """``rollouts`` copies of ``scene`` whose simulated agents follow guarded rollouts of ``ckpt`` (drawn at
    ``temperature``; 1 samples the guarded distribution itself)."""
    cur = scene.current_index
    res = rollout(
        ckpt,
        scene,
        rollouts,
        scene.num_steps - cur - 1,
        config=SamplingConfig(guard=True, seed=seed, temperature=temperature),
    )
    sim = scene.valid[:, cur]
    out = []
    for r in range(rollouts):
        xyh, valid = scene.xyh.copy(), scene.valid.copy()
        xyh[sim, cur + 1 :] = res.xyh[r, sim, cur + 1 :]
        valid[sim, cur + 1 :] = res.valid[r, sim, cur + 1 :]
        xyh[~valid] = 0.0
        out.append(replace(scene, xyh=xyh, valid=valid, scenario_id=f"{scene.scenario_id}-guarded{r}"))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", required=True, help="scene directories or files")
    p.add_argument("--out", required=True, help="output directory of the shards")
    p.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    p.add_argument("--rollouts", type=int, default=2, help="rollouts per scene")
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--temperature", type=float, default=DEFAULT_TEMPERATURE, help="sampling temperature")
    args = p.parse_args()
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    made: list[Scenario] = []
    for k, scene in enumerate(tqdm(SceneStore(args.data).scenes, desc="guarded rollouts")):
        made += guarded_scenes(ckpt, scene, args.rollouts, args.seed + k, args.temperature)
    out = Path(args.out)
    for i in range(0, len(made), SCENES_PER_SHARD):
        save_scenarios(out / f"guarded-{i // SCENES_PER_SHARD:05d}.scn.npz", made[i : i + SCENES_PER_SHARD])
    print(f"{len(made)} scenes in {out}")


if __name__ == "__main__":
    main()
