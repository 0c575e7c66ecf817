"""The ``trajeglish`` commands that sample and score the model (``evaluate``, ``brake-test``, ``rollout``),
registered by :func:`trajeglish_env.cli.build_parser`."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from trajeglish_env.cli_args import (
    NON_NEGATIVE,
    POSITIVE,
    add_dtype_args,
    non_negative_float,
    output_dir,
    positive_float,
    probability,
    scene_at,
)
from trajeglish_env.cli_scorecard import add_scorecard_command
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE, SamplingConfig
from trajeglish_env.sampler.subsets import SUBSET_RULES

GUARD_CHOICES = {"off": (False,), "on": (True,), "both": (False, True)}  # --guard: guarded sampling
BRAKE_NPCS = ("trajeglish", "trajeglish+guard", "idm", "replay", "constant_velocity")  # see brake_test.NPCS
AddCommand = Callable[..., argparse.ArgumentParser]  # build_parser's add(name, handler, help_text)


def checkpoints(items: list[str] | None) -> dict[str, Any]:
    """``[NAME=]PATH`` items (PATH ``shipped``: the pretrained model) -> {name: Checkpoint}; none -> the
    shipped pretrained model."""
    from trajeglish_env.checkpoint import load_named, load_pretrained

    ckpts, given = {}, {}
    for item in items or []:
        name, _, path = item.rpartition("=")
        ckpt = load_named(path)
        name = name or ckpt.config.variant.value
        if name in ckpts:  # the second replaced the first, silently
            raise ValueError(
                f"--ckpt {item}: the name {name!r} is taken by --ckpt {given[name]}; name each one "
                f"(--ckpt A=FILE --ckpt B=FILE)"
            )
        ckpts[name], given[name] = ckpt, item
    return ckpts or {"trajeglish": load_pretrained()}


def cmd_evaluate(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.distributed import init_ranks, rank_device
    from trajeglish_env.evaluation import EvalConfig, evaluate
    from trajeglish_env.sampler.config import SamplingConfig
    from trajeglish_env.sampler.rollouts import auto_processes

    device = rank_device()
    ranks = init_ranks(device)
    # with --submission the checkpoints are evaluated only when named
    ckpts = {} if args.submission and not args.ckpt else checkpoints(args.ckpt)
    if args.partial and args.partial not in ckpts:  # it failed after every method had run
        raise ValueError(f"--partial {args.partial}: expected one of the checkpoints {sorted(ckpts)}")
    for ckpt in ckpts.values():
        ckpt.model.to(device)
    config = EvalConfig(
        rollouts=args.rollouts,
        scenes=args.scenes,
        temperatures=tuple(args.temperature),
        sampling=SamplingConfig(
            top_p=args.top_p,
            cache_dtype=args.cache_dtype,
            compute_dtype=args.compute_dtype,
            subsets=args.subsets,
            **guard_rules(args, args.guard != "off"),
        ),
        metrics=args.metrics,
        seed=args.seed,
        guards=GUARD_CHOICES[args.guard],
        # one process per free core (looked at once), unless torchrun ranks share the cores already
        rollout_processes=args.processes or (auto_processes(args.rollouts) if ranks.world == 1 else 1),
    )
    partial = args.partial or ("trajeglish" if "trajeglish" in ckpts else next(iter(ckpts), None))
    result = evaluate(
        args.data,
        ckpts,
        config,
        output_dir(args.out),
        partial=partial,
        progress=not args.quiet,
        submission=args.submission,
        ranks=ranks,
    )
    result["_silent"] = not ranks.main  # under torchrun the main rank prints the merged table
    return result


def cmd_brake_test(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.brake_test import BrakeTestConfig, brake_test, markdown_table
    from trajeglish_env.env.scenes import load_bundle
    from trajeglish_env.sampler.config import SamplingConfig

    if args.data:
        from trajeglish_env.training.dataset import SceneStore

        scenes = list(SceneStore(args.data).scenes)
    else:
        bundle = load_bundle()
        scenes = [bundle.get(i) for i in range(len(bundle))]
    config = BrakeTestConfig(
        npcs=tuple(args.npc),
        episodes=args.episodes,
        steps=args.steps,
        max_gap=args.max_gap,
        seed=args.seed,
        sampling=SamplingConfig(
            args.temperature, args.top_p, args.cache_dtype, compute_dtype=args.compute_dtype
        ),
    )
    ckpt = next(iter(checkpoints([args.ckpt]).values())) if args.ckpt else None
    result = brake_test(scenes, config, ckpt, args.out, progress=not args.quiet)
    if not args.json:
        print(markdown_table(result), end="")
        return {key: result[key] for key in ("table", "plot")}
    return result


def cmd_long_rollouts(args: argparse.Namespace) -> dict[str, Any]:
    import json

    from trajeglish_env.evaluation import spread_indices
    from trajeglish_env.long_rollouts import LongRolloutConfig, long_rollout_rates, markdown_table, plot_rates
    from trajeglish_env.sampler.config import SamplingConfig
    from trajeglish_env.scenario_io import atomic_path
    from trajeglish_env.training.dataset import SceneStore

    every = SceneStore(args.data).scenes
    scenes = [every[k] for k in spread_indices(len(every), args.scenes)]
    config = LongRolloutConfig(
        seconds=args.seconds,
        rollouts=args.rollouts,
        split_s=args.split,
        guards=GUARD_CHOICES[args.guard],
        sampling=SamplingConfig(
            args.temperature, args.top_p, args.cache_dtype, compute_dtype=args.compute_dtype
        ),
        seed=args.seed,
    )
    ckpt = next(iter(checkpoints([args.ckpt] if args.ckpt else None).values()))
    result = long_rollout_rates(ckpt, scenes, config, progress=not args.quiet)
    out = output_dir(args.out)
    result["plot"] = plot_rates(result, out / "long_rollout_rates.png")
    table = markdown_table(result)
    for name, text in (("long_rollouts.json", json.dumps(result, indent=2)), ("long_rollouts.md", table)):
        with atomic_path(out / name) as tmp:
            tmp.write_text(text)
    if not args.json:
        print(table, end="")
        return {"plot": result["plot"], "table": str(out / "long_rollouts.md")}
    return result


def cmd_rollout(args: argparse.Namespace) -> dict[str, Any]:
    import numpy as np

    from trajeglish_env.render import VIDEO_SUFFIXES, RenderConfig, check_output, role_colors, save_render
    from trajeglish_env.sampler import rollout
    from trajeglish_env.sampler.config import SamplingConfig

    check_output(args.out, (".png", *VIDEO_SUFFIXES))  # before the rollout is sampled, not after
    scene = scene_at(args.scenario, args.index)
    ckpt = next(iter(checkpoints([args.ckpt] if args.ckpt else None).values()))
    horizon = args.horizon or scene.num_steps - scene.current_index - 1
    sampling = SamplingConfig(
        args.temperature,
        args.top_p,
        args.cache_dtype,
        seed=args.seed,
        compute_dtype=args.compute_dtype,
        guard=args.guard == "on",
        **guard_rules(args, args.guard == "on"),
    )
    res = rollout(ckpt, scene, 1, horizon, config=sampling)
    guard = args.guard == "on"
    out = save_render(
        scene,
        args.out,
        xyh=res.xyh[0],
        valid=res.valid[0],
        # the model's agents by class, the sdc (also the model's: full control) red; the log's grey
        colors=role_colors(scene, np.arange(scene.num_agents) == scene.sdc, res.controlled),
        config=RenderConfig(follow_sdc=args.follow_sdc, legend=args.legend),
        png_step=res.xyh.shape[2] - 1,  # a picture shows where the rollout ends, its last second in trails
        caption=f"Trajeglish rollout, guard {args.guard}, T = {args.temperature:g}",
    )
    return {
        "scene": scene.scenario_id,
        "agents": scene.num_agents,
        "horizon": horizon,
        "guard": guard,
        "green_rule": sampling.guard_green if guard else None,  # guard settings: None without it
        "road_ahead": sampling.guard_road_ahead if guard else None,
        "step_change": sampling.guard_step_change if guard else None,
        "stall_steps": sampling.guard_stall_steps if guard else None,
        "wrong_way_rule": sampling.guard_wrong_way if guard else None,
        "follow_decel": sampling.guard_follow_decel if guard else None,
        "out": str(out),
    }


def add_guard_rule_args(p: argparse.ArgumentParser, green_help: str) -> None:
    """The guard's rules: ``--no-green-rule``, ``--no-wrong-way-rule``, ``--road-ahead M``, ``--step-change
    M``, ``--stall-steps S`` and ``--follow-decel A`` (read by :func:`guard_rules`)."""
    p.add_argument("--no-green-rule", action="store_true", help=green_help)
    p.add_argument(
        "--no-wrong-way-rule",
        action="store_true",
        help="guarded vehicles may turn or drive onto a lane against every lane there "
        "(SamplingConfig.guard_wrong_way=False)",
    )
    p.add_argument(
        "--road-ahead",
        type=non_negative_float,
        metavar="M",
        help="metres of each candidate's kept-up motion the guard checks against the road edges "
        f"(SamplingConfig.guard_road_ahead; 0: the one-step road rule alone; default: the env's, "
        f"{SamplingConfig.guard_road_ahead:g})",
    )
    p.add_argument(
        "--step-change",
        type=non_negative_float,
        metavar="M",
        help="metres by which a guarded vehicle's forward step may change from its last one (SamplingConfig."
        f"guard_step_change; cyclists half; 0: no speed-change rule; default: the env's, "
        f"{SamplingConfig.guard_step_change:g})",
    )
    p.add_argument(
        "--stall-steps",
        type=NON_NEGATIVE,
        metavar="S",
        help="steps a guarded vehicle or cyclist that drove may stand with the way clear before it must set "
        "off (SamplingConfig.guard_stall_steps; 0: no stall rule; default: the env's, "
        f"{SamplingConfig.guard_stall_steps})",
    )
    p.add_argument(
        "--follow-decel",
        type=non_negative_float,
        metavar="A",
        help="deceleration (m/s^2) at which a guarded vehicle or cyclist must still be able to stop "
        "behind the box ahead (SamplingConfig.guard_follow_decel; 0: no following rule; default: the env's, "
        f"{SamplingConfig.guard_follow_decel:g})",
    )


def guard_rules(args: argparse.Namespace, guard: bool) -> dict[str, Any]:
    """The :class:`SamplingConfig` fields of the guard's rule flags; a rule flag given where no method is
    guarded is refused (it would change nothing)."""
    given = [
        flag
        for flag, value in (
            ("--no-green-rule", args.no_green_rule),
            ("--no-wrong-way-rule", args.no_wrong_way_rule),
            ("--road-ahead", args.road_ahead is not None),
            ("--step-change", args.step_change is not None),
            ("--stall-steps", args.stall_steps is not None),
            ("--follow-decel", args.follow_decel is not None),
        )
        if value
    ]
    if given and not guard:
        raise ValueError(f"{', '.join(given)}: the guard's rules, but --guard off samples without the guard")
    default = SamplingConfig()
    return {
        "guard_green": not args.no_green_rule,
        "guard_wrong_way": not args.no_wrong_way_rule,
        "guard_road_ahead": default.guard_road_ahead if args.road_ahead is None else args.road_ahead,
        "guard_step_change": default.guard_step_change if args.step_change is None else args.step_change,
        "guard_stall_steps": default.guard_stall_steps if args.stall_steps is None else args.stall_steps,
        "guard_follow_decel": default.guard_follow_decel if args.follow_decel is None else args.follow_decel,
    }


def add_eval_commands(add: AddCommand) -> None:
    """Register the sampling and scoring commands with ``build_parser``'s ``add``."""
    p = add("evaluate", cmd_evaluate, "realism of rollouts vs the log and baselines on held-out scenes")
    p.add_argument("--data", nargs="+", required=True, help="held-out scene directories")
    p.add_argument(
        "--ckpt",
        action="append",
        help="[NAME=]checkpoint or 'shipped' (repeatable; default: the shipped model)",
    )
    p.add_argument("--rollouts", type=POSITIVE, default=8)
    p.add_argument(
        "--scenes",
        type=POSITIVE,
        default=16,
        help="N scenes spread evenly over the data (all of them when fewer)",
    )
    p.add_argument(
        "--temperature",
        type=positive_float,
        nargs="+",
        default=[DEFAULT_TEMPERATURE],
        help="sampling temperatures to evaluate (default: the env's NPC default)",
    )
    p.add_argument("--top-p", type=probability, default=1.0)
    add_dtype_args(p)
    p.add_argument(
        "--metrics",
        choices=("2024", "2024-era", "2025"),
        default="2025",
        help="WOSAC config: 2025, 2024 (its weights under the current official code), or 2024-era (as "
        "the 2024 leaderboard scored: time to collision of every evaluated object, not vehicles only)",
    )
    p.add_argument(
        "--processes",
        type=POSITIVE,
        help="processes each scene's model rollouts are split over, the same rollouts (default: one per "
        "core other processes leave free; 1 under torchrun)",
    )
    p.add_argument(
        "--guard",
        choices=("off", "on", "both"),
        default="both",
        help="guarded sampling: methods NAME@T=t (off) and NAME+guard@T=t (on); default: both",
    )
    add_guard_rule_args(p, "guarded methods without the green-light rule (SamplingConfig.guard_green=False)")
    p.add_argument(
        "--subsets",
        choices=SUBSET_RULES,
        default=SamplingConfig.subsets,
        help="how scenes larger than the model's context are split into subsets of agents "
        "(SamplingConfig.subsets; default: the env's)",
    )
    p.add_argument("--partial", help="checkpoint name for the partial-control experiment")
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument("--out", default="out/evaluate", help="directory for the table and plots")
    p.add_argument(
        "--submission",
        help="also score the rollouts of this submission (shard, .tar.gz or directory); then only the "
        "checkpoints named with --ckpt are sampled",
    )

    p = add(
        "brake-test",
        cmd_brake_test,
        "reactivity: an ego brakes hard to a stop in front of following NPCs; how often is it rear-ended?",
    )
    p.add_argument("--npc", nargs="+", choices=BRAKE_NPCS, default=list(BRAKE_NPCS[:4]), help="NPC policies")
    p.add_argument("--episodes", type=POSITIVE, default=22, help="episodes per NPC policy")
    p.add_argument("--steps", type=int, default=60, help="steps per episode")
    p.add_argument("--max-gap", type=float, default=25.0, help="followers at most this far behind (m)")
    p.add_argument("--data", nargs="+", help="scene directories or files (default: the bundled scenes)")
    p.add_argument("--ckpt", help="model of the Trajeglish NPCs (default: the shipped model)")
    p.add_argument("--temperature", type=float, default=DEFAULT_TEMPERATURE)
    p.add_argument("--top-p", type=float, default=1.0)
    add_dtype_args(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/brake_test", help="directory for the JSON, table and plot")

    p = add(
        "long-rollouts",
        cmd_long_rollouts,
        "rollouts far past the log: collision and off-road onsets per agent-second before/after 8 s",
    )
    p.add_argument("--data", nargs="+", required=True, help="scene directories or files")
    p.add_argument("--scenes", type=POSITIVE, default=16, help="scenes, spread over the data")
    p.add_argument(
        "--seconds", type=positive_float, default=30.0, help="rollout length after the current step"
    )
    p.add_argument("--split", type=positive_float, default=8.0, help="window boundary (s)")
    p.add_argument("--rollouts", type=POSITIVE, default=2, help="rollouts per scene")
    p.add_argument("--guard", choices=("off", "on", "both"), default="both", help="guarded sampling")
    add_sampling_args(p)
    p.add_argument("--out", default="out/long_rollouts", help="directory for the JSON, table and plot")

    p = add("rollout", cmd_rollout, "sample one rollout of a scene and render it")
    p.add_argument("--scenario", required=True, help="scenario file (*.scn.npz)")
    p.add_argument("--index", type=NON_NEGATIVE, default=0)
    p.add_argument("--out", required=True, help="output .gif, .mp4 or .png")
    p.add_argument(
        "--horizon", type=POSITIVE, help="steps after the current one (default: to the end of the log)"
    )
    add_sampling_args(p)
    p.add_argument("--follow-sdc", action="store_true")
    p.add_argument("--legend", action="store_true", help="a key of the colours in the lower left corner")
    p.add_argument("--guard", choices=("on", "off"), default="on", help="guarded sampling (default: on)")
    add_guard_rule_args(p, "the guard without its green-light rule")
    add_map_coverage_command(add)
    add_scorecard_command(add)


def cmd_map_coverage(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.map_coverage import CoverageConfig, coverage_by_kind, coverage_table
    from trajeglish_env.training.dataset import SceneStore

    every = SceneStore(args.data).scenes
    scenes = list(every)[: args.scenes] if args.scenes else list(every)
    ckpt = next(iter(checkpoints([args.ckpt] if args.ckpt else None).values()))
    strides = args.stride or [ckpt.config.map_stride]
    by_kind = coverage_by_kind(scenes, ckpt.config, strides, CoverageConfig(horizon=args.horizon))
    result = {
        "scenes": len(scenes),
        "map_select": ckpt.config.map_select,
        "max_polylines": ckpt.config.max_polylines,
        "points_per_polyline": ckpt.config.points_per_polyline,
        "strides": strides,
        "by_kind": by_kind,
        "table": "\n" + coverage_table(by_kind),
    }
    if not args.json:  # the table says it
        del result["by_kind"]
    return result


def add_map_coverage_command(add: AddCommand) -> None:
    """``trajeglish map-coverage``: how much of the road ahead a model's windows show (see
    :mod:`~trajeglish_env.map_coverage`)."""
    p = add(
        "map-coverage",
        cmd_map_coverage,
        "how much of each vehicle's next logged path lies on the lane chunks a model's window shows",
    )
    p.add_argument("--data", nargs="+", required=True, help="scene directories or files")
    p.add_argument("--scenes", type=POSITIVE, help="the first N scenes (default: all)")
    p.add_argument("--ckpt", help="the model whose windows are measured (default: the shipped model)")
    p.add_argument("--stride", type=POSITIVE, nargs="+", help="map strides to measure (default: the model's)")
    p.add_argument("--horizon", type=POSITIVE, default=80, help="future steps looked at (10 a second)")


def add_sampling_args(p: argparse.ArgumentParser) -> None:
    """The checkpoint and sampling options of a command that samples one model."""
    p.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    p.add_argument("--temperature", type=positive_float, default=DEFAULT_TEMPERATURE)
    p.add_argument("--top-p", type=probability, default=1.0)
    add_dtype_args(p)
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
