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

or, with ``--guard off --temperature 1 --clean-horizon H``, the model's own samples with what led to a
failure cut out (filtered self-imitation): each simulated agent's rolled-out states from ``H`` steps before
its first collision (a pair of pedestrians excepted) or, for a vehicle, its first off-road state on are
invalid, so training reads only the rolled-out motion that stayed clear:

    python scripts/guarded_rollout_scenes.py --data out/train_hw --out out/clean_hw --rollouts 2 \
        --guard off --temperature 1 --clean-horizon 10
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.metrics.road_edges import OFFROAD_THRESHOLD, RoadEdges, distance_to_road_edge
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE, SamplingConfig
from trajeglish_env.sampler.rollouts import rollout
from trajeglish_env.scenario import ROAD_EDGE_KINDS, AgentKind, Scenario
from trajeglish_env.scenario_io import atomic_path, save_scenarios
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


def first_failures(scene: Scenario) -> np.ndarray:
    """``[N]`` the first step after the current one at which each agent valid at the current step collides
    (boxes overlap; not a pair of pedestrians, nor a pair already overlapping at the current step) or, a
    vehicle, is off the road (WOSAC's off-road rule; not one off it already at the current step, nor on a map
    without road edges); ``num_steps`` where it never does, -1 for the others."""
    cur, n, t = scene.current_index, scene.num_agents, scene.num_steps
    sim = np.flatnonzero(scene.valid[:, cur])
    out = np.full(n, -1, np.int64)
    out[sim] = t
    xyh, valid = scene.xyh[sim], scene.valid[sim]
    i, j = np.triu_indices(len(sim), 1)
    ped = scene.kind[sim] == AgentKind.PEDESTRIAN
    keep = ~(ped[i] & ped[j])
    keep &= ~box_collisions(xyh[i, cur], scene.size[sim][i], xyh[j, cur], scene.size[sim][j])
    i, j = i[keep], j[keep]
    hit = box_collisions(xyh[i, cur:], scene.size[sim][i, None], xyh[j, cur:], scene.size[sim][j, None]) & (
        valid[i, cur:] & valid[j, cur:]
    )  # [pairs, T - cur]
    bad = np.zeros((len(sim), t - cur), bool)
    np.logical_or.at(bad, i, hit)
    np.logical_or.at(bad, j, hit)
    vehicle = scene.kind[sim] == AgentKind.VEHICLE
    lines = [line for line in scene.polylines(ROAD_EDGE_KINDS) if len(line) >= 2]
    if vehicle.any() and lines:  # a map without road edges: collisions alone
        states = xyh[vehicle, cur:]
        xyz = np.concatenate([states[..., :2], np.zeros_like(states[..., :1])], axis=-1)
        box = np.concatenate([scene.size[sim][vehicle], np.ones((int(vehicle.sum()), 1))], axis=-1)
        edges = RoadEdges.from_polylines(lines)
        off = (
            distance_to_road_edge(xyz, states[..., 2], box[:, None], valid[vehicle, cur:], edges)
            > OFFROAD_THRESHOLD
        )
        # a vehicle off the road in the log at the current step is left alone
        bad[vehicle] |= off & ~off[:, :1]
    bad[:, 0] = False  # the current step is the log's
    first = np.where(bad.any(axis=1), cur + bad.argmax(axis=1), t)
    out[sim] = first
    return out


def cut_failures(scene: Scenario, horizon: int) -> tuple[Scenario, int]:
    """``scene`` with each simulated agent's states from ``horizon`` steps before its first failure
    (:func:`first_failures`) on invalid (never the current step or before); and how many agents were cut."""
    first = first_failures(scene)
    cut = first >= 0
    cut &= first < scene.num_steps
    start = np.maximum(first - horizon, scene.current_index + 1)
    steps = np.arange(scene.num_steps)
    drop = cut[:, None] & (steps[None] >= start[:, None])
    valid = scene.valid & ~drop
    xyh = np.where(valid[..., None], scene.xyh, 0.0)
    return replace(scene, xyh=xyh, valid=valid), int(cut.sum())


def _shown(value: object) -> str:
    """``value`` for an error message: a long list by its length."""
    text = repr(value)
    return f"{len(value)} entries" if isinstance(value, list) and len(text) > 80 else text


def settings_guard(out: Path, settings: dict[str, object]) -> None:
    """Refuse to resume into ``out`` when its shards were written with other settings (``settings.json``),
    naming each field that differs, or by a run that recorded none; where no shard is there yet, record
    ``settings`` (a first run that failed before writing one may be rerun with others)."""
    path = out / "settings.json"
    shards = sorted(out.glob("guarded-*.scn.npz"))
    if shards and not path.exists():
        raise SystemExit(f"{out} holds {len(shards)} shards but no settings.json; choose another --out")
    if shards:
        try:
            before = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"{path}: unreadable ({e}); remove {out} or choose another --out") from None
        differ = {k: (before.get(k), v) for k, v in settings.items() if before.get(k) != v}
        if differ:
            named = "; ".join(f"{k}: {_shown(a)} there, {_shown(b)} now" for k, (a, b) in differ.items())
            raise SystemExit(f"{out} holds rollouts made with other settings ({named}); choose another --out")
        return
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(settings, indent=2))


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
    p.add_argument(
        "--clean-horizon",
        type=int,
        help="cut each agent's rolled-out states from this many steps before its first collision or "
        "off-road state on (filtered self-imitation; default: keep every state)",
    )
    args = p.parse_args()
    if args.rollouts < 1:
        p.error(f"--rollouts must be at least 1, got {args.rollouts}")
    if args.clean_horizon is not None and args.clean_horizon < 0:
        p.error(f"--clean-horizon must be 0 or more steps, got {args.clean_horizon}")
    ckpt = load_checkpoint(args.ckpt) if args.ckpt else load_pretrained()
    scenes = SceneStore(args.data).scenes
    settings = {k: v for k, v in vars(args).items() if k != "out"}
    settings["data"] = [str(Path(d).resolve()) for d in args.data]
    settings["ckpt"] = str(Path(args.ckpt).resolve()) if args.ckpt else "shipped"
    settings["scenes"] = [scene.scenario_id for scene in scenes]  # the input may not change under a resume
    settings_guard(Path(args.out), settings)
    out = Path(args.out)
    per_shard = max(1, SCENES_PER_SHARD // args.rollouts)  # input scenes per output shard
    cut = simulated = made = 0
    for first in tqdm(range(0, len(scenes), per_shard), desc="rollout shards"):
        path = out / f"guarded-{first // per_shard:05d}.scn.npz"
        if path.exists():  # written by an earlier run: resume after it
            continue
        shard: list[Scenario] = []
        for k in range(first, min(first + per_shard, len(scenes))):
            rolled = guarded_scenes(
                ckpt,
                scenes[k],
                args.rollouts,
                args.seed + k,
                args.temperature,
                args.guard == "on",
                args.as_rollout,
            )
            if args.clean_horizon is not None:
                for r, scene in enumerate(rolled):
                    rolled[r], n = cut_failures(scene, args.clean_horizon)
                    cut += n
                    simulated += int(scene.valid[:, scene.current_index].sum())
            shard += rolled
        save_scenarios(path, shard)  # atomic: a killed run loses at most the shard it was on
        made += len(shard)
    if args.clean_horizon is not None:
        print(f"agents cut at a failure: {cut} of {simulated} ({cut / max(simulated, 1):.3f}) in this run")
    print(f"{made} scenes written to {out} in this run")


if __name__ == "__main__":
    main()
