"""The ``trajeglish scorecard`` command (:mod:`trajeglish_env.scorecard`), registered by
:func:`trajeglish_env.cli_eval.add_eval_commands`."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from trajeglish_env.cli_args import NON_NEGATIVE, POSITIVE, output_dir

AddCommand = Callable[..., argparse.ArgumentParser]


def scorecard_checkpoints(items: list[str] | None, shipped: bool) -> dict[str, Any]:
    """``shipped`` (unless left out) and every ``NAME=PATH`` of ``--ckpt``; names must differ."""
    from trajeglish_env.checkpoint import load_checkpoint, load_pretrained

    ckpts: dict[str, Any] = {"shipped": load_pretrained()} if shipped else {}
    for item in items or []:
        name, sep, path = item.rpartition("=")
        if not sep or not name:
            raise ValueError(f"--ckpt {item!r}: expected NAME=PATH (the name labels its column)")
        if name in ckpts:
            raise ValueError(f"--ckpt {item!r}: the name {name!r} is taken; give each checkpoint its own")
        ckpts[name] = load_checkpoint(path)
    if not ckpts:
        raise ValueError("scorecard: --no-shipped leaves no checkpoint; name one with --ckpt NAME=PATH")
    return ckpts


def cmd_scorecard(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.sampler.rollouts import auto_processes
    from trajeglish_env.scorecard import PARTS, QUICK, ScorecardConfig, run_scorecard

    base = QUICK if args.quick else ScorecardConfig()
    changes: dict[str, Any] = {
        "parts": tuple(args.parts or PARTS),
        "seed": args.seed,
        "more_seeds": tuple(args.more_seeds or ()),
        "womd": args.womd,
    }
    if args.rollouts is not None:
        changes["rollouts"] = args.rollouts
    # one process per free core (looked at once), as `evaluate` does
    changes["processes"] = args.processes or auto_processes(changes.get("rollouts", base.rollouts))
    config = replace(base, **changes)
    ckpts = scorecard_checkpoints(args.ckpt, not args.no_shipped)
    result = run_scorecard(ckpts, config, output_dir(args.out), args.data_dir, progress=not args.quiet)
    if not args.json:
        print(open(result["markdown"]).read(), end="")
        return {"markdown": result["markdown"], "met": result["met"]}
    return result


def add_scorecard_command(add: AddCommand) -> None:
    from trajeglish_env.scorecard import PARTS

    p = add(
        "scorecard",
        cmd_scorecard,
        "every NPC-quality target (realism per source, model alone vs constant velocity, partial "
        "control, brake test, 30 s rollouts, WOMD, demo, tokenization) for the shipped model and others",
    )
    p.add_argument(
        "--ckpt", action="append", help="NAME=checkpoint to score beside the shipped model (repeatable)"
    )
    p.add_argument("--no-shipped", action="store_true", help="leave the shipped model out")
    p.add_argument("--parts", nargs="+", choices=PARTS, help="parts to compute (default: all)")
    p.add_argument("--quick", action="store_true", help="tiny scene sets and rollouts: a smoke run")
    p.add_argument("--rollouts", type=POSITIVE, help="rollouts per held-out scene (default 8)")
    p.add_argument(
        "--processes",
        type=POSITIVE,
        help="processes the rollouts and generation are split over (default: one per core other processes "
        "leave free)",
    )
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument(
        "--more-seeds",
        nargs="+",
        type=NON_NEGATIVE,
        metavar="SEED",
        help="the highway-env and SUMO parts again at these rollout seeds: their rows show the mean (judged) "
        "and the range (the model-alone rows move by up to 0.03 between seeds)",
    )
    p.add_argument("--womd", help="WOMD scenario file (default: the shared one)")
    p.add_argument(
        "--data-dir", help="where the held-out scenes are generated (default: OUT/data; reused when there)"
    )
    p.add_argument(
        "--out", default="out/scorecard", help="results: scorecard.json/.md, each part saved as it finishes"
    )
