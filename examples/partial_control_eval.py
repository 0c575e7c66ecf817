"""Partial-control evaluation: one external agent (the sdc, driven by a policy) among NPCs that are either
Trajeglish or the log replayed, with the ego acting first or last within each timestep.

    python examples/partial_control_eval.py --episodes 20            # shipped model, bundled scenes
    python examples/partial_control_eval.py --smoke --npc-a idm      # quick check without a model

Acting first, the NPCs of each step see the ego's move (they can react within the step); acting last,
the ego sees theirs. Replay NPCs never react. Prints collision rate, off-road rate and progress per setting.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from policies import ConstantVelocityPolicy, IDMPolicy, ReplayPolicy, evaluate
from trajeglish_env.env import TrajeglishNPC, raw_env
from trajeglish_env.env.scenes import load_bundle

EGOS = {"replay": ReplayPolicy, "idm": IDMPolicy, "constant_velocity": ConstantVelocityPolicy}


def _or_nan(value: float | None) -> float:
    """A summary's mean, NaN where it is undefined (None: no agent with a goal)."""
    return float("nan") if value is None else value


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--episodes", type=int, default=20, help="episodes per setting (one per bundled scene)"
    )
    parser.add_argument("--ego", default="idm", choices=sorted(EGOS))
    parser.add_argument("--npc-a", default="trajeglish", help="reactive NPCs (trajeglish, idm, ...)")
    parser.add_argument("--npc-b", default="replay", help="the non-reactive reference")
    parser.add_argument(
        "--ckpt", "--checkpoint", dest="checkpoint", help="Trajeglish model (default: the shipped one)"
    )
    parser.add_argument("--max-cycles", type=int, default=None)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--smoke", action="store_true", help="2 episodes of 6 steps")
    args = parser.parse_args(argv)
    if args.smoke:
        args.episodes, args.max_cycles = 2, args.max_cycles or 6
    scenes = [load_bundle().get(i).scenario_id for i in range(len(load_bundle()))]
    results: dict[str, dict[str, float]] = {}
    for npc_name in (args.npc_a, args.npc_b):
        npc = TrajeglishNPC(args.checkpoint) if npc_name == "trajeglish" else npc_name
        for order in ("first", "last"):
            env = raw_env(npc=npc, order=order, max_cycles=args.max_cycles)
            summary = evaluate(env, EGOS[args.ego](), args.episodes, seed=0, scenes=scenes)
            results[f"{npc_name}/{order}"] = summary
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(f"ego: {args.ego}; {args.episodes} episodes per setting")
        print(f"{'NPCs/ego order':>24} {'collision':>9} {'off-road':>8} {'progress m':>10} {'route':>6}")
        for name, m in results.items():
            print(
                f"{name:>24} {m['collision_rate']:9.2f} {m['offroad_rate']:8.2f} "
                f"{m['mean_progress_m']:10.1f} {_or_nan(m['mean_route_fraction']):6.2f}"
            )
    return results


if __name__ == "__main__":
    main()
