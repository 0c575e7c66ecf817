"""Quickstart: your own ego policy in the AEC loop, Trajeglish NPCs around it, and a video.

    python examples/quickstart.py                      # shipped model, a bundled scene, out/quickstart.gif
    python examples/quickstart.py --npc idm --smoke    # no model needed, a few steps

The ego policy below reads only the vector observation (layout: trajeglish_env.env.observations): it
follows the route points ahead and keeps a target speed, braking for an agent ahead in its path.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import trajeglish_env
from trajeglish_env.env import EnvConfig, TrajeglishNPC
from trajeglish_env.env.observations import EGO_FEATURES, NEIGHBOUR_FEATURES

CONFIG = EnvConfig()
K, Q, R = CONFIG.obs.neighbours, CONFIG.obs.route_points, CONFIG.obs.radius


def keep_route_policy(obs: np.ndarray, target_speed: float = 12.0) -> np.ndarray:
    """Continuous action (acceleration, steering) in [-1, 1]^2 from a vector observation."""
    speed = obs[0] * 30.0
    route = obs[-2 * Q :].reshape(Q, 2) * R
    aim = route[1]  # the route point 10 m ahead
    steer = np.clip(2.0 * np.arctan2(aim[1], max(aim[0], 1.0)), -1.0, 1.0)
    others = obs[EGO_FEATURES : EGO_FEATURES + NEIGHBOUR_FEATURES * K].reshape(K, NEIGHBOUR_FEATURES)
    x, y = others[:, 1] * R, others[:, 2] * R
    ahead = (others[:, 0] == 1) & (x > 0) & (np.abs(y) < 2.5)
    gap = x[ahead].min() if ahead.any() else np.inf
    wanted = min(target_speed, max(gap - 8.0, 0.0) / 1.5)  # about 1.5 s of headway, 8 m standstill gap
    accel = np.clip((wanted - speed) / 3.0, -1.0, 1.0)
    return np.array([accel, steer], dtype=np.float32)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="highway-exit-999001", help="bundled scene id or index")
    parser.add_argument(
        "--npc", default="trajeglish", choices=("trajeglish", "idm", "replay", "constant_velocity")
    )
    parser.add_argument(
        "--ckpt",
        "--checkpoint",
        dest="checkpoint",
        help="Trajeglish model for the NPCs (default: the shipped one)",
    )
    parser.add_argument(
        "--steps", type=int, default=None, help="episode length (default: the rest of the log)"
    )
    parser.add_argument("--out", default="out/quickstart.gif")
    parser.add_argument("--smoke", action="store_true", help="8 steps, a small video")
    args = parser.parse_args(argv)
    npc = TrajeglishNPC(args.checkpoint) if args.npc == "trajeglish" else args.npc
    steps = 8 if args.smoke else args.steps
    env = trajeglish_env.env(
        npc=npc, max_cycles=steps, render_mode="rgb_array", render_size=240 if args.smoke else 480
    )
    env.reset(seed=0, options={"scene": int(args.scene) if args.scene.isdigit() else args.scene})

    # the AEC loop: one external agent (the sdc) acting in turn among the NPCs
    total, info = 0.0, {}
    for _agent in env.agent_iter():
        obs, reward, terminated, truncated, info = env.last()
        total += reward
        env.step(None if terminated or truncated else keep_route_policy(obs))

    video = env.unwrapped.save_video(Path(args.out))
    result = {
        "scene": env.unwrapped.scenario.scenario_id,
        "steps": env.unwrapped.sim.steps,
        "return": round(total, 3),
        "progress_m": round(info.get("progress_m", 0.0), 1),
        "collision_steps": info.get("collision_steps", 0),
        "offroad_steps": info.get("offroad_steps", 0),
        "video": str(video),
    }
    print(result)
    return result


if __name__ == "__main__":
    main()
