"""The environment on a Waymo Open Motion Dataset scene: read a scenario TFRecord (no TensorFlow needed),
put an IDM ego in place of the sdc, let the NPCs drive, and write a video.

    python examples/womd_scene.py --tfrecord /path/to/scenario.tfrecord
    python examples/womd_scene.py --smoke --npc idm     # the shared one-scenario sample, a few steps

Bring your own data: any WOMD scenario TFRecord works as is, or convert many with
``trajeglish convert-womd FILE... --out DIR`` and pass ``scenes=DIR`` to the env.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from policies import IDMPolicy, play_episode
from trajeglish_env.benchmark.womd import locate_womd
from trajeglish_env.env import TrajeglishNPC, raw_env
from trajeglish_env.sources.womd import read_womd


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--tfrecord",
        help="WOMD scenario TFRecord (default: the shared sample, found under $TRAJEGLISH_SHARED, else in "
        "a shared/ folder beside the checkout or the current directory)",
    )
    parser.add_argument(
        "--npc", default="trajeglish", choices=("trajeglish", "idm", "replay", "constant_velocity")
    )
    parser.add_argument("--checkpoint", help="Trajeglish model for the NPCs (default: the shipped one)")
    parser.add_argument(
        "--steps", type=int, default=None, help="episode length (default: the 8 s of the log)"
    )
    parser.add_argument("--out", default="out/womd_scene.gif")
    parser.add_argument("--smoke", action="store_true", help="6 steps, a small video")
    args = parser.parse_args(argv)
    path = locate_womd(args.tfrecord)
    if not isinstance(path, Path):
        raise SystemExit(path.replace("--womd", "--tfrecord"))
    scene = next(read_womd(path))
    npc = TrajeglishNPC(args.checkpoint) if args.npc == "trajeglish" else args.npc
    env = raw_env(
        [scene], npc=npc, max_cycles=6 if args.smoke else args.steps, render_size=240 if args.smoke else 640
    )
    result = play_episode(env, IDMPolicy(), seed=0, video=args.out)
    ego = next(iter(result.returns))
    summary = {
        "scenario": scene.scenario_id,
        "agents": scene.num_agents,
        "npcs": int(env.sim.npc.sum()),
        "steps": result.steps,
        "ego": ego,
        "ego_return": round(result.returns[ego], 3),
        "ego_progress_m": round(result.progress_m[ego], 1),
        "ego_collided": result.collision[ego],
        "ego_offroad": result.offroad[ego],
        "video": str(result.video),
    }
    print(summary)
    return summary


if __name__ == "__main__":
    main()
