"""``trajeglish demo``: the shipped model drives the NPCs of a bundled scene around an external ego (a
rule-based controller), then the episode is written as a video and summarised (ego outcome, NPC
collision and off-road rates, speed)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from trajeglish_env.checkpoint import CheckpointError
from trajeglish_env.env.aec import raw_env
from trajeglish_env.env.config import RewardConfig, TrajeglishNPC
from trajeglish_env.env.controllers import RuleBasedController
from trajeglish_env.env.rewards import collisions, offroad


def npc_outcomes(raw: Any) -> dict[str, float]:
    """Fraction of NPCs that collided with anyone / drove off-road at some step of the episode."""
    sim = raw.sim
    sc, cur, end = raw.scenario, raw.scenario.current_index, sim.t
    npcs = np.flatnonzero(sim.npc)
    hit = np.zeros(len(npcs), dtype=bool)
    off = np.zeros(len(npcs), dtype=bool)
    for t in range(cur + 1, end + 1):  # one vectorized check per step
        valid = sim.driver.valid[:, t]
        hit |= collisions(sim.driver.xyh[:, t], valid, sc.size, npcs)
        off |= offroad(sim.driver.xyh[npcs, t], sc.size[npcs], sc.kind[npcs], sim.edges, 0.5) & valid[npcs]
    n = max(len(npcs), 1)
    return {"npc_collision_rate": float(hit.sum() / n), "npc_offroad_rate": float(off.sum() / n)}


def run_demo(
    out: Path,
    scene: str = "highway-intersection-999000",
    seed: int = 0,
    steps: int | None = None,
    checkpoint: str | None = None,
    ego: str = "idm",
    order: str = "first",
    video_format: str = "gif",
    progress: bool = True,
) -> dict[str, Any]:
    """Play one episode and write ``out/demo.<format>``; returns the episode's metrics (a scene the
    bundle lacks is refused before ``out`` is made, naming ``--scene``)."""
    from trajeglish_env.env.scenes import scene_index, scene_set

    try:
        scene_index(int(scene) if scene.isdigit() else scene, scene_set(None))
    except (KeyError, ValueError) as exc:
        raise ValueError(f"--scene {scene}: {exc}") from None
    out.mkdir(parents=True, exist_ok=True)
    try:
        env = raw_env(
            npc=TrajeglishNPC(checkpoint),
            order=order,
            max_cycles=steps,
            # the whole episode plays, also past the end of the ego's route (--steps beyond the log)
            reward=RewardConfig(
                terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
            ),
        )
    except CheckpointError as exc:
        if checkpoint is None:  # the shipped model is missing: say how to give one
            raise CheckpointError(f"{exc}; or run the demo with --ckpt PATH") from exc
        raise
    env.reset(seed=seed, options={"scene": int(scene) if scene.isdigit() else scene})
    sim = env.sim
    assert sim is not None
    controller = RuleBasedController(ego)
    agent = env.agent_selection
    ego_index = env.agent_index(agent)
    total, start, shown = 0.0, time.perf_counter(), 0
    first: float | None = None  # when the first timestep ended (it pays the first use's compiling)
    for name in env.agent_iter():
        _, reward, terminated, truncated, _ = env.last()
        total += float(reward)
        env.step(None if terminated or truncated else controller.action(env, name))
        if first is None and sim.steps >= 1:
            first = time.perf_counter()
        if progress and sim.steps % 10 == 0 and sim.steps != shown:  # once per step (dead steps repeat it)
            shown = sim.steps
            print(f"step {sim.steps}/{sim.horizon}", end="\r", flush=True, file=sys.stderr)
    end = time.perf_counter()
    first = end if first is None else first
    row = sim.route_row[ego_index]
    video = env.save_video(out / f"demo.{video_format}")
    ckpt = env.checkpoint
    return {
        "scene": env.scenario.scenario_id,
        "agents": int(env.scenario.num_agents),
        "npcs": int(sim.npc.sum()),
        "ego": agent,
        "ego_policy": ego,
        "order": order,
        "steps": int(sim.steps),
        "ego_return": round(total, 4),
        "ego_collision_steps": int(sim.collision_steps[row]),
        "ego_offroad_steps": int(sim.offroad_steps[row]),
        "ego_progress_m": round(float(sim.progress[row]), 2),
        "ego_route_fraction": round(float(sim.progress[row] / max(sim.routes.length[row], 1e-6)), 3),
        **{k: round(v, 3) for k, v in npc_outcomes(env).items()},
        # after the first timestep, whose first use of the guard's compiled kernels compiles them in a fresh
        # install (seconds, once: cached) and loads them later: reported apart
        "env_steps_per_s": round((sim.steps - 1) / (end - first), 2)
        if sim.steps > 1 and end > first
        else None,
        "first_step_s": round(first - start, 2),
        "model": str(getattr(ckpt, "path", None) or "in-memory checkpoint"),
        "video": str(video),
    }
