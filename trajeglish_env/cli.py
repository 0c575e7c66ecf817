"""The ``trajeglish`` command line: one sub-command per job, ``--json`` for machine-readable results.

Progress bars and logs go to stderr; with ``--json`` the only thing on stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
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
    add_budget_and_mix_args,
    add_map_args,
    at_least_one,
    below_one,
    interrupt_on_sigterm,
    interrupted_note,
    one_line,
    output_dir,
    positive_float,
    probability,
    scene_at,
    unit_float,
    with_map_args,
)
from trajeglish_env.cli_bench import add_bench_command
from trajeglish_env.cli_eval import add_eval_commands, checkpoints
from trajeglish_env.cli_mass_terms import add_mass_term_arguments, mass_term_settings
from trajeglish_env.cli_tokenizer import add_tokenizer_commands
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
    files = [Path(f) for f in args.files]
    result = convert_womd(files, output_dir(args.out), not args.quiet and ranks.main, args.workers, ranks)
    result["_silent"] = not ranks.main  # under torchrun the main rank prints the merged report
    if result.get("failed"):
        result["exit_code"] = 1
    return result


def cmd_render(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.render import RenderConfig, save_render

    scene = scene_at(args.scene, args.index)
    config = RenderConfig(view_radius=args.radius, follow_sdc=args.follow_sdc, show_ids=args.ids)
    out = save_render(scene, args.out, config=config, fps=args.fps)
    return {"scene": scene.scenario_id, "source": scene.source, "agents": scene.num_agents, "out": str(out)}


def cmd_train(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.checkpoint import load_checkpoint, load_named
    from trajeglish_env.checkpoint_reading import fine_tune_note, is_reading, training_start
    from trajeglish_env.distributed import init_ranks, rank_device
    from trajeglish_env.model.config import preset
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
    from trajeglish_env.training.kind_repeat import parse_repeat
    from trajeglish_env.training.train import TrainConfig, train

    vocabulary = MotionVocabulary.load(args.vocab) if args.vocab else None
    init = load_named(args.init) if args.init else None
    last = Path(args.out) / "last.pt"  # a resumed run goes on with its own model and vocabulary
    own = args.resume and last.is_file() and not (args.preset or args.variant or args.vocab)
    if (
        init is not None
        and is_reading(init)
        and vocabulary is None
        and not own
        and os.environ.get("RANK", "0") == "0"
    ):
        print(fine_tune_note(args.init, init), file=sys.stderr)  # what changes: never silently
    init, vocabulary = training_start(init, vocabulary)  # a reading extension: its base, on all it reads
    overrides: dict[str, Any] = {"variant": args.variant or "trajeglish"}
    overrides.update({"vocab_size": vocabulary.size} if vocabulary is not None else {})
    if own:
        model_config, vocabulary = (resumed := load_checkpoint(last)).config, resumed.vocabulary
    elif init is not None and args.preset is None and args.variant is None:
        model_config = init.config  # fine-tuning: the checkpoint's model unless asked otherwise
    else:
        model_config = preset(args.preset or "small", **overrides)
    if init is not None and vocabulary is not None and vocabulary.size != init.config.vocab_size:
        # a vocabulary extending the checkpoint's (check_init says if it does not)
        model_config = dataclasses.replace(model_config, vocab_size=vocabulary.size, token_bias=True)
    if args.signal_input:
        model_config = dataclasses.replace(model_config, signal_input=True)
    if args.neighbour_input:
        model_config = dataclasses.replace(model_config, neighbour_input=True)
    if args.lane_input:
        model_config = dataclasses.replace(model_config, lane_input=True)
    model_config = with_map_args(model_config, args)
    config = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        warmup_steps=args.warmup,
        seed=args.seed,
        num_workers=args.workers,
        val_every=args.val_every,
        checkpoint_every=args.checkpoint_every,
        noisy_inputs=not args.no_noise,
        shard_cache=args.shard_cache,
        signal_lr_scale=args.signal_lr_scale,
        repeat=parse_repeat(args.repeat),
        closed_loop_top_k=args.closed_loop_top_k,
        closed_loop_recovery=args.closed_loop_recovery,
        closed_loop_along_recovery=args.closed_loop_along_recovery,
        closed_loop_teacher_forced=not args.closed_loop_only,
        interaction_weight=args.interaction_weight,
        bend_weight=args.bend_weight,
        **mass_term_settings(args),
        history_dropout=args.history_dropout,
        noise_on_device=args.noise_on_device,
        precision=args.precision,
    )
    ranks = init_ranks(rank_device())
    result = train(
        args.data,
        output_dir(args.out),
        model_config,
        config,
        vocabulary,
        args.val_data,
        args.resume,
        not args.quiet,
        init=init,
        time_limit=None if args.minutes is None else args.minutes * 60.0,
        fit_steps=args.fit_steps,
        overwrite=args.overwrite,
    )
    result["_silent"] = not ranks.main  # under torchrun the main rank prints the run's result
    return result


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
    parser = ArgParser(prog="trajeglish", description=__doc__)
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
    p.add_argument("--fps", type=POSITIVE, default=10)

    add_tokenizer_commands(add, sub)

    p = add("train", cmd_train, "train a Trajeglish model on scene shards (torchrun for several processes)")
    p.add_argument("--data", nargs="+", required=True, help="scene directories")
    p.add_argument(
        "--out", required=True, help="run directory (checkpoints, metrics.csv, training_curve.png)"
    )
    p.add_argument(
        "--preset", choices=("tiny", "small", "paper"), help="model size (default: small, or --init's)"
    )
    p.add_argument(
        "--variant",
        choices=("trajeglish", "no-intra", "marginal", "no-map"),
        help="model variant (default: trajeglish, or --init's)",
    )
    p.add_argument("--vocab", help="vocabulary file (default: the shipped 384-token vocabulary, or --init's)")
    p.add_argument(
        "--init",
        help="start from this trained checkpoint, or 'shipped' for the shipped model (fine-tuning; same "
        "config and vocabulary; a model that reads more tokens than it draws learns to draw them all)",
    )
    add_map_args(p)
    p.add_argument(
        "--signal-input",
        action="store_true",
        help="the model reads the traffic signals' states (ModelConfig.signal_input); with --init, the "
        "checkpoint's model is extended with it",
    )
    p.add_argument(
        "--neighbour-input",
        action="store_true",
        help="every decoder position also reads its agent's velocity and nearest neighbours' relative "
        "states (ModelConfig.neighbour_input); with --init, the checkpoint's model is extended with it",
    )
    p.add_argument(
        "--lane-input",
        action="store_true",
        help="every decoder position also reads the lane centres and road edges around its agent, in the "
        "agent's frame (ModelConfig.lane_input); with --init, the checkpoint's model is extended with it",
    )
    p.add_argument(
        "--signal-lr-scale",
        type=positive_float,
        default=1.0,
        help="learning-rate multiplier of the signal embedding (it starts at zero inside an --init model)",
    )
    p.add_argument("--steps", type=POSITIVE, default=2000, help="optimisation steps")
    p.add_argument("--batch-size", type=POSITIVE, default=16, help="global batch size (split over processes)")
    p.add_argument("--lr", type=positive_float, default=5e-4)
    p.add_argument("--warmup", type=NON_NEGATIVE, default=100)
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument("--workers", type=NON_NEGATIVE, default=1, help="DataLoader worker processes")
    p.add_argument("--val-data", help="held-out scenes (default: every 20th training scene)")
    p.add_argument("--val-every", type=POSITIVE, default=200)
    p.add_argument("--checkpoint-every", type=POSITIVE, default=200)
    p.add_argument("--no-noise", action="store_true", help="argmin input tokens (no noisy tokenization)")
    p.add_argument(
        "--closed-loop-top-k",
        type=NON_NEGATIVE,
        default=0,
        help="CAT-K closed-loop fine-tuning: every window is rolled out with the model's K most likely "
        "tokens (the one nearest the log), then trained to return to the log (0: teacher forcing)",
    )
    p.add_argument(
        "--closed-loop-recovery",
        type=probability,
        default=0.2,
        help="share of the rolled-out state's sideways and heading offset from the log a closed-loop target "
        "closes per step",
    )
    p.add_argument(
        "--closed-loop-along-recovery",
        type=unit_float,
        default=0.2,
        help="the same along the log's heading (0: targets move as the log does and keep the offset)",
    )
    p.add_argument(
        "--closed-loop-only",
        action="store_true",
        help="train on the closed-loop windows alone (default: beside the batch's teacher-forced ones)",
    )
    add_mass_term_arguments(p)
    p.add_argument(
        "--interaction-weight",
        type=at_least_one,
        default=1.0,
        help="loss weight of the tokens of agents closing in on the agent ahead (within 4 s at the closing "
        "speed, or under 0.6 s headway; 1: plain likelihood; validation NLL stays plain)",
    )
    p.add_argument(
        "--bend-weight",
        type=at_least_one,
        default=1.0,
        help="loss weight of the tokens where the lane ahead turns away from an agent's current motion "
        "(needs --lane-input; 1: plain likelihood; validation NLL stays plain)",
    )
    p.add_argument(
        "--history-dropout",
        type=below_one,
        default=0.0,
        help="share of each window's agents whose input tokens are all hidden, so that their next tokens are "
        "learned from the current states the model reads (needs --neighbour-input; default 0)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue from RUN/last.pt exactly where it stopped, with its own model and vocabulary; pass "
        "the run's schedule flags again (--steps, --batch-size, ...: a difference is refused, naming it)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="start a new run in an --out that holds one (without it, or --resume, that is refused)",
    )
    add_budget_and_mix_args(p)
    p.add_argument(
        "--shard-cache",
        type=NON_NEGATIVE,
        default=0,
        help="keep at most K shards in memory per loading process, scenes drawn K shards at a time "
        "(large data sets; default 0: every scene in memory)",
    )

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
    and propagates with its traceback. With
    ``TRAJEGLISH_TRACEBACK=1`` bad input propagates too (to see where a ValueError came from).
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
            raise
        message = one_line(str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc))
        if os.environ.get("RANK", "0") == "0":  # every rank meets the same bad input: the main one says so
            if getattr(args, "json", False):
                print(json.dumps({"error": message, "type": type(exc).__name__}))
            print(f"{args.command_name}: error: {message}", file=sys.stderr)
        return EXIT_BAD_INPUT
    code = int(result.pop("exit_code", 0))
    if not result.pop("_silent", False):  # non-main ranks of a torchrun job print nothing
        _print_result(result, args.json)
    return code


if __name__ == "__main__":
    sys.exit(main())
