"""The ``trajeglish`` command line: one sub-command per job, ``--json`` for machine-readable results.

Progress bars and logs go to stderr; with ``--json`` the only thing on stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from trajeglish_env.cli_args import (
    EXIT_BAD_INPUT,
    EXIT_INTERRUPTED,
    NON_NEGATIVE,
    POSITIVE,
    USER_ERRORS,
    ArgParser,
    UsageError,
    interrupt_on_sigterm,
    interrupted_note,
    one_line,
    output_dir,
    positive_float,
    scene_at,
)
from trajeglish_env.cli_bench import add_bench_command
from trajeglish_env.cli_eval import add_eval_commands, checkpoints
from trajeglish_env.cli_tokenizer import add_tokenizer_commands
from trajeglish_env.cli_train import add_train_command
from trajeglish_env.cli_womd import add_womd_commands

Handler = Callable[[argparse.Namespace], dict[str, Any]]


def _print_result(result: dict[str, Any], as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, indent=2, default=str))
        return
    for key, value in result.items():
        print(f"{key}: {value}")


# ---------------------------------------------------------------------------------------- commands
def cmd_generate(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.distributed import init_ranks
    from trajeglish_env.sources.generation import GenerationConfig, generate

    kinds = tuple(k.strip() for k in (args.kinds or "").split(",") if k.strip())  # "grid, spider" too
    if args.kinds is not None and not kinds:
        raise ValueError(f"--kinds {args.kinds!r}: no kind named (leave --kinds out for every kind)")
    ranks = init_ranks()
    config = GenerationConfig(args.source, args.scenes, args.seed, kinds, args.scenes_per_shard)
    result = generate(config, output_dir(args.out), args.workers, not args.quiet and ranks.main, ranks)
    result["_silent"] = not ranks.main  # under torchrun the main rank prints the merged summary
    return result


def cmd_convert_womd(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.distributed import init_ranks
    from trajeglish_env.sources.womd_convert import convert_womd

    ranks = init_ranks()
    files = list(args.files)  # as given: a repeat is named in the user's spelling (``./a`` and ``a``)
    result = convert_womd(files, output_dir(args.out), not args.quiet and ranks.main, args.workers, ranks)
    result["_silent"] = not ranks.main  # under torchrun the main rank prints the merged report
    if result.get("failed"):
        result["exit_code"] = 1
    return result


def cmd_render(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.render import RenderConfig, save_render

    scene = scene_at(args.scene, args.index)
    config = RenderConfig(
        view_radius=args.radius, follow_sdc=args.follow_sdc, show_ids=args.ids, legend=args.legend
    )
    out = save_render(scene, args.out, config=config, fps=args.fps)
    now = int(scene.valid[:, scene.current_index].sum())  # the picture's "agents=K now of N"
    return {
        "scene": scene.scenario_id,
        "source": scene.source,
        "agents": scene.num_agents,
        "agents_now": now,
        "out": str(out),
    }


def cmd_curves(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.training.curves import plot_runs

    runs = {}
    for item in args.runs:
        name, _, path = item.rpartition("=")
        runs[name or Path(path).name] = path
    return plot_runs(runs, args.out)


def cmd_nll(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.training.density import evaluate_nll

    return evaluate_nll(
        checkpoints(args.ckpt),
        args.data,
        args.windows,
        args.seed,
        args.unigram_data,
        args.plots,
        cache_dtypes=tuple(args.cache_dtype or ()),
        compute_dtypes=tuple(args.compute_dtype or ()),
    )


def cmd_demo(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.env.demo import run_demo

    return run_demo(
        out=output_dir(args.out),
        scene=args.scene,
        seed=args.seed,
        steps=args.steps,
        checkpoint=args.checkpoint,
        ego=args.ego,
        order=args.order,
        video_format=args.format,
        progress=not args.quiet,
    )


# ---------------------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    from trajeglish_env import __version__

    parser = ArgParser(prog="trajeglish", description=__doc__)
    parser.add_argument("--version", action="version", version=f"trajeglish_env {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name: str, handler: Handler, help_text: str, parent: Any = sub) -> argparse.ArgumentParser:
        p = parent.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--json", action="store_true", help="print one JSON object with the results on stdout")
        p.add_argument("--quiet", action="store_true", help="no progress bar")
        p.set_defaults(handler=handler, command_name=p.prog)  # errors name the (sub)command
        commands[p.prog] = p
        return p

    commands: dict[str, argparse.ArgumentParser] = {}
    parser.set_defaults(commands=commands)

    p = add("generate", cmd_generate, "generate scenes with a built-in simulator into shard files")
    p.add_argument("--scenes", type=POSITIVE, required=True, help="number of scenes")
    p.add_argument("--out", required=True, help="output directory (resumes if it holds a partial run)")
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument("--workers", type=POSITIVE, default=1, help="parallel processes")
    p.add_argument("--source", choices=("highway", "sumo"), default="highway")
    p.add_argument(
        "--kinds",
        help="comma-separated scene kinds (default: all kinds of the source; highway also takes KIND+stop, "
        "the kind with a hard stop event, see sources/highway_stops.py)",
    )
    p.add_argument("--scenes-per-shard", type=POSITIVE, default=8)

    p = add("convert-womd", cmd_convert_womd, "convert Waymo Open Motion Dataset TFRecords to shard files")
    p.add_argument("files", nargs="+", help="WOMD scenario TFRecord files")
    p.add_argument("--out", required=True)
    p.add_argument("--workers", type=POSITIVE, default=1, help="processes per rank (one file each at a time)")

    p = add("render", cmd_render, "draw a scene as a PNG picture or a GIF/MP4 animation")
    p.add_argument("scene", help="scenario file (*.scn.npz)")
    p.add_argument("--out", required=True, help="output .png, .gif or .mp4")
    p.add_argument("--index", type=NON_NEGATIVE, default=0, help="which scene of a multi-scene shard")
    p.add_argument("--radius", type=positive_float, default=None, help="half-width of the view in metres")
    p.add_argument("--follow-sdc", action="store_true", help="keep the sdc at the centre")
    p.add_argument("--ids", action="store_true", help="label agents with their track ids")
    p.add_argument("--legend", action="store_true", help="a key of the colours in the lower left corner")
    p.add_argument("--fps", type=POSITIVE, default=10)

    add_tokenizer_commands(add, sub)

    add_train_command(add)

    p = add("curves", cmd_curves, "validation NLL curves of several training runs in one picture")
    p.add_argument("runs", nargs="+", help="[NAME=]run directory (its metrics.csv)")
    p.add_argument("--out", required=True, help="PNG file to write")

    p = add(
        "nll", cmd_nll, "held-out NLL per token: per class, vs agents-before and context length, vs unigram"
    )
    p.add_argument("--data", nargs="+", required=True, help="held-out scene directories")
    p.add_argument(
        "--ckpt",
        action="append",
        help="[NAME=]checkpoint or 'shipped' (repeatable; default: the shipped model)",
    )
    p.add_argument("--windows", type=POSITIVE, default=256)
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument("--unigram-data", nargs="+", help="training scenes to fit the unigram baseline on")
    p.add_argument("--plots", help="directory for the analysis plots")
    p.add_argument(
        "--cache-dtype",
        nargs="+",
        choices=("float32", "bfloat16"),
        help="also compute the NLL through the decoding cache in these dtypes (what bfloat16 NPCs cost)",
    )
    p.add_argument(
        "--compute-dtype",
        nargs="+",
        choices=("float32", "bfloat16"),
        help="also through each cache (default float32) with the linear layers multiplying in these dtypes",
    )

    add_eval_commands(add)
    add_womd_commands(add)

    p = add(
        "demo",
        cmd_demo,
        "the main job: the shipped model drives a built-in scene around an external ego; video + metrics",
    )
    p.add_argument("--out", default="out/demo")
    p.add_argument("--scene", default="highway-intersection-999000", help="bundled scene id or index")
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument(
        "--steps",
        type=POSITIVE,
        default=None,
        help="episode length (default: the rest of the log; longer episodes go on past the log's end)",
    )
    p.add_argument(
        "--ckpt",
        "--checkpoint",
        dest="checkpoint",
        help="model for the NPCs (default: the shipped pretrained model); --checkpoint is the old spelling",
    )
    p.add_argument("--ego", choices=("idm", "replay", "constant_velocity"), default="idm")
    p.add_argument("--order", choices=("first", "last", "random"), default="first")
    p.add_argument("--format", choices=("gif", "mp4"), default="gif")

    add_bench_command(add)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``trajeglish`` console script; returns the process exit code.

    Bad input (:data:`USER_ERRORS`) is one line on stderr (and an ``error`` object on stdout with
    ``--json``) and exit code 2; Ctrl-C or SIGTERM one line and exit code 130; any other exception is a bug
    and propagates with its traceback. With ``TRAJEGLISH_TRACEBACK=1`` bad input's traceback is printed
    before that line (to see where a ValueError came from), still exit code 2.
    """
    words = list(sys.argv[1:] if argv is None else argv)
    try:
        args, extra = build_parser().parse_known_args(words)
        if extra:  # named by the command they were given to, not by the top-level parser
            args.commands[args.command_name].error(f"unrecognized arguments: {' '.join(extra)}")
    except UsageError as exc:
        if "--json" in words:
            print(json.dumps({"error": exc.message, "type": "UsageError"}))
        raise
    try:
        with interrupt_on_sigterm():
            result = args.handler(args)
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM: worker pools and temporary folders are torn down
        if os.environ.get("TRAJEGLISH_TRACEBACK", "") not in ("", "0"):
            raise
        if os.environ.get("RANK", "0") == "0":  # under torchrun one line, not one per rank
            print(f"{args.command_name}: interrupted; {interrupted_note(args)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except USER_ERRORS as exc:
        if os.environ.get("TRAJEGLISH_TRACEBACK", "") not in ("", "0"):
            traceback.print_exc()
        message = one_line(str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc))
        rank = os.environ.get("RANK", "0")
        if rank == "0":  # the JSON object once per job (stdout stays one object)
            if getattr(args, "json", False):
                print(json.dumps({"error": message, "type": type(exc).__name__}))
            print(f"{args.command_name}: error: {message}", file=sys.stderr)
        else:  # a rank's own error (a shard only it reads) is named too
            print(f"{args.command_name} [rank {rank}]: error: {message}", file=sys.stderr)
        return EXIT_BAD_INPUT
    code = int(result.pop("exit_code", 0))
    if not result.pop("_silent", False):  # non-main ranks of a torchrun job print nothing
        _print_result(result, args.json)
    return code


if __name__ == "__main__":
    sys.exit(main())
