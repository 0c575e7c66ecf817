"""`trajeglish train`'s options for the loss terms against colliding and off-road candidate tokens
(training/blocked_mass.py, training/offroad_mass.py), and the ``TrainConfig`` fields they set."""

from __future__ import annotations

import argparse
from typing import Any

from trajeglish_env.cli_args import POSITIVE, non_negative_float


def add_mass_term_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--collision-*`` and ``--offroad-*`` options of ``train``."""
    p.add_argument(
        "--collision-weight",
        type=non_negative_float,
        default=0.0,
        help="weight of a loss term against the probability on candidate tokens that would collide (0: off; "
        "scenes of a model's own rollouts, scripts/guarded_rollout_scenes.py --guard off, train by it alone "
        "after their current step)",
    )
    p.add_argument(
        "--collision-horizon",
        type=POSITIVE,
        default=1,
        help="steps each candidate is kept up for --collision-weight (1: the guard's one-step rule; H: also "
        "moves that stay on a collision course with an agent's states of the next H steps)",
    )
    p.add_argument(
        "--collision-rolled-out-only",
        action="store_true",
        help="apply --collision-weight to the rolled-out targets of own-rollout scenes alone (the logged "
        "targets keep plain likelihood)",
    )
    p.add_argument(
        "--collision-sources",
        nargs="+",
        default=[],
        metavar="SOURCE",
        help="apply --collision-weight to the windows of these scene sources alone, e.g. sumo (a model's own "
        "rollouts of a source count as it; default: every window)",
    )
    p.add_argument(
        "--collision-form",
        choices=("mass", "versus-target"),
        default="mass",
        help="the form of --collision-weight's term: mass, -log(1 - m) of the colliding mass m (standing "
        "lowers it too), or versus-target, log(1 + m / p) of m against the target token's probability p "
        "(only the target and the colliding tokens move)",
    )
    p.add_argument(
        "--offroad-weight",
        type=non_negative_float,
        default=0.0,
        help="weight of a loss term against the probability on candidate tokens that would take a vehicle "
        "off the road (the guard's road-edge rule, on the scene's road edges; 0: off)",
    )
    p.add_argument(
        "--offroad-positions",
        type=POSITIVE,
        default=32,
        help="vehicle target positions per window, drawn at random, that --offroad-weight checks",
    )
    p.add_argument(
        "--offroad-horizon",
        type=POSITIVE,
        default=1,
        help="steps a candidate's move is kept up (the same template repeated) for --offroad-weight's rule: "
        "a move that takes a corner off the road within them counts as off-road (1: the next step only)",
    )
    p.add_argument(
        "--offroad-form",
        choices=("mass", "versus-target"),
        default="mass",
        help="the form of --offroad-weight's term, as --collision-form (versus-target: m the off-road mass "
        "against the target token's probability)",
    )


def mass_term_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The ``TrainConfig`` fields of the parsed ``--collision-*`` and ``--offroad-*`` options."""
    return {
        "collision_weight": args.collision_weight,
        "collision_horizon": args.collision_horizon,
        "collision_rolled_out_only": args.collision_rolled_out_only,
        "collision_sources": tuple(args.collision_sources),
        "collision_form": args.collision_form.replace("-", "_"),
        "offroad_weight": args.offroad_weight,
        "offroad_positions": args.offroad_positions,
        "offroad_horizon": args.offroad_horizon,
        "offroad_form": args.offroad_form.replace("-", "_"),
    }
