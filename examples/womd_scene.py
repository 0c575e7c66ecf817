"""The environment on a Waymo Open Motion Dataset scene: read a scenario TFRecord (no TensorFlow needed),
put an IDM ego in place of the sdc, let the NPCs drive, and write a video.

    python examples/womd_scene.py --tfrecord /path/to/scenario.tfrecord
    python examples/womd_scene.py --smoke --npc idm     # the shared one-scenario sample, a few steps
    python examples/womd_scene.py --tfrecord FILE --index 3     # the 4th scenario of a many-scenario file

Bring your own data: any WOMD scenario TFRecord works as is, or convert many with
``trajeglish convert-womd FILE... --out DIR`` and pass ``scenes=DIR`` to the env.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from policies import IDMPolicy, play_episode
from trajeglish_env.benchmark.womd import locate_womd
from trajeglish_env.env import TrajeglishNPC, raw_env
from trajeglish_env.scenario import Scenario
from trajeglish_env.sources.womd import WomdFormatError, read_womd_at


def load_scene(path: Path, index: int = 0) -> Scenario:
    """The ``index``-th scenario of a WOMD TFRecord file; a bad file or index is one line on stderr and exit
    code 2 (:class:`SystemExit`)."""
    try:
        return read_womd_at(path, index)
    except (WomdFormatError, OSError) as exc:
        message = str(exc).replace(f"; index {index} is out of range", f"; --index {index} is out of range")
        if isinstance(exc, OSError) and str(path) not in message:
            message = f"{path}: {exc.strerror or exc}"
        print(f"womd_scene.py: error: {' '.join(message.split())}", file=sys.stderr)
        raise SystemExit(2) from None


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
    parser.add_argument(
        "--ckpt",
        "--checkpoint",
        dest="checkpoint",
        help="Trajeglish model for the NPCs (default: the shipped one)",
    )
    parser.add_argument(
        "--steps", type=int, default=None, help="episode length (default: the 8 s of the log)"
    )
    parser.add_argument(
        "--index", type=int, default=0, help="which scenario of the file to drive (0-based, default 0)"
    )
    parser.add_argument("--out", default="out/womd_scene.gif")
    parser.add_argument("--smoke", action="store_true", help="6 steps, a small video")
    args = parser.parse_args(argv)
    path = locate_womd(args.tfrecord)
    if not isinstance(path, Path):
        raise SystemExit(path.replace("--womd", "--tfrecord"))
    if args.index < 0:
        parser.error(f"--index must be >= 0, got {args.index}")
    scene = load_scene(path, args.index)
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
