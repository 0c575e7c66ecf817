"""``trajeglish train``: its arguments, the training settings they make, and the command."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from trajeglish_env.cli_args import (
    NON_NEGATIVE,
    POSITIVE,
    add_budget_and_mix_args,
    add_map_args,
    at_least_one,
    below_one,
    output_dir,
    positive_float,
    probability,
    unit_float,
    with_map_args,
)
from trajeglish_env.cli_mass_terms import add_mass_term_arguments, mass_term_settings

if TYPE_CHECKING:
    from trajeglish_env.training.train import TrainConfig

AddCommand = Callable[..., argparse.ArgumentParser]


def train_config_of(args: argparse.Namespace) -> TrainConfig:
    """The training settings the parsed ``train`` arguments ask for."""
    from trajeglish_env.training.kind_repeat import parse_repeat
    from trajeglish_env.training.train import TrainConfig

    return TrainConfig(
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


def default_train_args() -> argparse.Namespace:
    """``train``'s arguments left at their defaults (what a flag not given means): a resume takes the run's
    own value for every setting these give."""
    parser = argparse.ArgumentParser(add_help=False)
    add_train_arguments(parser)
    return parser.parse_args(["--data", "-", "--out", "-"])


def check_resumable(args: argparse.Namespace) -> None:
    """``--resume`` of an ``--out`` holding no run (a mistyped path) is refused before anything loads,
    not started from scratch (a folder with ``model.pt`` alone gets the training's own refusal)."""
    out = output_dir(args.out)
    if args.resume and not args.overwrite and not any((out / f).is_file() for f in ("last.pt", "model.pt")):
        raise FileNotFoundError(
            f"--resume: no run to resume in {out} (no {out / 'last.pt'}); to start a new run there, "
            "leave out --resume"
        )


def cmd_train(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.checkpoint import load_checkpoint, load_named
    from trajeglish_env.checkpoint_reading import fine_tune_note, is_reading, training_start
    from trajeglish_env.distributed import init_ranks, rank_device
    from trajeglish_env.model.config import preset
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, load_default_tokenizer
    from trajeglish_env.training.train import train

    check_resumable(args)
    if args.vocab == "shipped":  # the package's own 384-token vocabulary, wherever it is installed
        vocabulary = load_default_tokenizer()
    else:
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
    config = train_config_of(args)
    last_exists = args.resume and last.is_file()
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
        resume_defaults=train_config_of(default_train_args()) if last_exists else None,
    )
    result["_silent"] = not ranks.main  # under torchrun the main rank prints the run's result
    return result


def add_train_command(add: AddCommand) -> None:
    """The ``train`` sub-command."""
    p = add("train", cmd_train, "train a Trajeglish model on scene shards (torchrun for several processes)")
    add_train_arguments(p)


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    """Every ``train`` flag."""
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
    p.add_argument(
        "--vocab",
        help="vocabulary file, or 'shipped' for the shipped 384-token vocabulary (default: it, or --init's)",
    )
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
        help="continue from RUN/last.pt exactly where it stopped, with its own model, vocabulary and "
        "settings (flags at their default values take the run's, listed on stderr; one given with another "
        "value that differs from the run's is refused, naming it; an --out without last.pt is refused)",
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
