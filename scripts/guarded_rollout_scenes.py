"""Rollouts of a model as scene shards: each scene's simulated agents (those valid at its current step) get
the future of one rollout (guarded by default) instead of the log's. Data for fine-tuning a model on its own
guarded behaviour (the distillation experiment of docs/evaluation.md):

    python scripts/guarded_rollout_scenes.py --data out/train_hw --out out/guarded_hw --rollouts 2
    trajeglish train --data out/train_hw out/guarded_hw --init shipped --lr 1e-4 --steps 600 --out runs/d

or, with ``--guard off --as-rollout``, the model's own unguarded states for the colliding-mass term of
``trajeglish train --collision-weight`` (their sources end ``+rollout``: past their current step they are not
likelihood targets; training/blocked_mass.py):

    python scripts/guarded_rollout_scenes.py --data out/train_hw --out out/own_hw --rollouts 1 \
        --guard off --as-rollout
    trajeglish train --data out/train_hw out/own_hw --init shipped --collision-weight 1 --out runs/c
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
from trajeglish_env.training.dataset import ROLLOUT_SOURCE, SceneStore

SCENES_PER_SHARD = 16


def guarded_scenes(
    ckpt: object,
    scene: Scenario,
    rollouts: int,
    seed: int,
    temperature: float = DEFAULT_TEMPERATURE,
    guard: bool = True,
    as_rollout: bool = False,
) -> list[Scenario]:
    """``rollouts`` copies of ``scene`` whose simulated agents follow rollouts of ``ckpt`` (drawn at
    ``temperature``; 1 samples the guarded distribution itself; ``guard`` False: the model alone), their
    source marked as a model's rollout (:data:`ROLLOUT_SOURCE`) with ``as_rollout``."""
    cur = scene.current_index
    res = rollout(
        ckpt,
        scene,
        rollouts,
        scene.num_steps - cur - 1,
        config=SamplingConfig(guard=guard, seed=seed, temperature=temperature),
    )
    sim = scene.valid[:, cur]
    out = []
    for r in range(rollouts):
        xyh, valid = scene.xyh.copy(), scene.valid.copy()
        xyh[sim, cur + 1 :] = res.xyh[r, sim, cur + 1 :]
        valid[sim, cur + 1 :] = res.valid[r, sim, cur + 1 :]
        xyh[~valid] = 0.0
        source = scene.source + ROLLOUT_SOURCE if as_rollout else scene.source
        name = f"{scene.scenario_id}-{'guarded' if guard else 'alone'}{r}"
        out.append(replace(scene, xyh=xyh, valid=valid, scenario_id=name, source=source))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", required=True, help="scene directories or files")
    p.add_argument("--out", required=True, help="output directory of the shards")
    p.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    p.add_argument("--rollouts", type=int, default=2, help="rollouts per scene")
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--temperature", type=float, default=DEFAULT_TEMPERATURE, help="sampling temperature")
    p.add_argument("--guard", choices=("on", "off"), default="on", help="guarded sampling (off: model alone)")
    p.add_argument(
        "--as-rollout",
        action="store_true",
        help="mark the scenes as a model's rollouts (source + '+rollout'): train --collision-weight then "
        "trains on them by its colliding-mass term alone past their current step",
    )
    args = p.parse_args()
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    made: list[Scenario] = []
    for k, scene in enumerate(tqdm(SceneStore(args.data).scenes, desc="rollouts")):
        made += guarded_scenes(
            ckpt, scene, args.rollouts, args.seed + k, args.temperature, args.guard == "on", args.as_rollout
        )
    out = Path(args.out)
    for i in range(0, len(made), SCENES_PER_SHARD):
        save_scenarios(out / f"guarded-{i // SCENES_PER_SHARD:05d}.scn.npz", made[i : i + SCENES_PER_SHARD])
    print(f"{len(made)} scenes in {out}")


if __name__ == "__main__":
    main()
