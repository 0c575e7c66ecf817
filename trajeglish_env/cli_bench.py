"""The ``trajeglish bench`` command (the benchmark suite of :mod:`trajeglish_env.benchmark.suite`),
registered by :func:`trajeglish_env.cli.build_parser`."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from trajeglish_env.benchmark.suite import SECTIONS, BenchConfig
from trajeglish_env.cli_args import POSITIVE, auto_or_at_least
from trajeglish_env.cli_eval import GUARD_CHOICES
from trajeglish_env.cli_womd import AddCommand
from trajeglish_env.sampler.config import COMPUTE_DTYPES

FULL_BATCHES = BenchConfig().batches  # the batched env's scene counts of a full run
QUICK_BATCHES = (1, 8)  # a smoke run's (--quick without --batches): B = 256 is no smoke test


def cmd_bench(args: argparse.Namespace) -> dict[str, Any]:
    """Run the suite as configured on the command line; print its digest (or the JSON document)."""
    from trajeglish_env.benchmark.suite import run_suite, summary_lines
    from trajeglish_env.scenario_io import atomic_path

    if args.threads != "auto" and not (args.threads.isdigit() and int(args.threads) >= 1):
        raise ValueError(f"--threads must be 'auto' or a positive integer, got {args.threads!r}")
    threads = args.threads if args.threads == "auto" else int(args.threads)
    if args.womd is not None and not Path(args.womd).is_file():  # a file the user named must be there
        raise FileNotFoundError(f"--womd {args.womd}: no such WOMD scenario file")
    if {"env", "busy"} & set(args.sections):
        from trajeglish_env.benchmark.workloads import benchmark_scenes

        try:  # before any timing: the env runs would fail in their worker after it
            benchmark_scenes(args.agents)
        except ValueError as err:
            raise ValueError(
                f"--agents {args.agents}: {err} (the env runs cut bundled scenes to it)"
            ) from None
    config = BenchConfig(
        batches=tuple(args.batches or (QUICK_BATCHES if args.quick else FULL_BATCHES)),
        agents=args.agents,
        env_steps=args.env_steps,
        env_min_seconds=args.env_min_seconds,
        torch_threads=threads,
        cache_dtype=args.cache_dtype,
        compute_dtype=args.compute_dtype,
        sections=tuple(args.sections),
        quick=args.quick,
        guards=GUARD_CHOICES[args.guard],
        womd=args.womd,
        split=not args.no_split,
        device=args.device,
        split_processes=args.split_processes,
    )

    def write(doc: dict[str, Any]) -> None:  # after every run: a suite stopped early keeps its figures
        if args.out:
            with atomic_path(args.out) as tmp:
                tmp.write_text(json.dumps(doc, indent=2))

    result = run_suite(config, progress=not args.quiet, on_update=write)
    write(result)
    if args.json:
        return result
    print("\n".join(summary_lines(result)))
    return {"written": args.out} if args.out else {}


def add_bench_command(add: AddCommand) -> None:
    """Register ``bench`` with the parser's ``add``."""
    p = add("bench", cmd_bench, "the benchmark suite: speed of every stage, batched env vs highway-env")
    p.add_argument(
        "--batches",
        type=POSITIVE,
        nargs="+",
        help=f"scenes per batched env (default: {' '.join(map(str, FULL_BATCHES))}; with --quick "
        f"{' '.join(map(str, QUICK_BATCHES))})",
    )
    p.add_argument("--agents", type=POSITIVE, default=24, help="agents per scene")
    p.add_argument(
        "--env-steps",
        type=POSITIVE,
        default=None,
        help="timed steps per batched-env run with Trajeglish NPCs (default: one window cycle of the model, "
        "re-priming included)",
    )
    p.add_argument(
        "--env-min-seconds",
        type=float,
        default=BenchConfig.env_min_seconds,
        help="each batched-env run is repeated from resets until its timed steps last this long (default "
        "%(default)s s; one window cycle of a single scene lasts about 0.3 s)",
    )
    p.add_argument("--threads", default="auto", help="torch threads of the batched env (or 'auto')")
    p.add_argument(
        "--cache-dtype",
        choices=("bfloat16", "float32"),
        default="bfloat16",
        help="decoder cache dtype of the env and busy runs (the rollout, womd and aec runs: the defaults)",
    )
    p.add_argument(
        "--compute-dtype",
        choices=COMPUTE_DTYPES,
        default="auto",
        help="dtype the NPC model's linear layers multiply in, in the env and busy runs (auto: bfloat16 "
        "for batches of 2 rows or more where the CPU has it natively; the rollout, womd and aec runs: the "
        "defaults)",
    )
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS, help="what to measure")
    p.add_argument("--quick", action="store_true", help="tiny workloads (a smoke run)")
    p.add_argument(
        "--guard",
        choices=GUARD_CHOICES,
        default="both",
        help="Trajeglish NPCs of the env runs without (off) and/or with (on) guarded sampling",
    )
    p.add_argument(
        "--womd",
        help="the womd section's WOMD scenario file (default: data/womd/motion_data_one_scenario.tfrecord "
        "of the shared folder: $TRAJEGLISH_SHARED, else shared/ beside the checkout; none: skipped)",
    )
    p.add_argument(
        "--device",
        default="cpu",
        help="torch device of the env runs' NPC model (cpu, cuda, cuda:1): the GPU figures of issue 16",
    )
    p.add_argument(
        "--no-split",
        action="store_true",
        help="skip the env and busy runs whose scenes are split over worker processes (processes='auto')",
    )
    p.add_argument(
        "--split-processes",
        default="auto",
        type=auto_or_at_least(2),
        help="worker processes of the env section's split runs (default auto; a count with --device cuda "
        "spawns that many GPU workers)",
    )
    p.add_argument("--out", help="also write the JSON document here (atomically)")
