"""The ``trajeglish tokenizer`` commands (fit, eval, extend), registered by
:func:`trajeglish_env.cli.build_parser`."""

from __future__ import annotations

import argparse
from typing import Any

from trajeglish_env.cli_args import (
    NON_NEGATIVE,
    POSITIVE,
    add_cover_args,
    output_dir,
    output_file,
    positive_float,
)
from trajeglish_env.cli_womd import AddCommand
from trajeglish_env.tokenizer.extend import VEHICLE_COVER_RADIUS
from trajeglish_env.tokenizer.fit import VOCAB_SIZES


def cmd_tokenizer_fit(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.tokenizer.fit import fit_from_directory

    output_file(args.out, "--out", "vocab.npz")  # before the fit, not after it
    return fit_from_directory(
        args.data,
        vocab_size=args.vocab,
        seed=args.seed,
        out=args.out,
        trials=args.trials,
        coverage=not args.no_coverage,
        min_data_share=args.data_share,
        cover_radius=args.cover_radius,
    )


def cmd_tokenizer_eval(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.tokenizer.fit import METHODS, evaluate_directory

    return evaluate_directory(
        args.data,
        vocab_sizes=tuple(args.vocab or (128, 256, 384, 512)),
        fit_data=args.fit_data,
        out_dir=output_dir(args.out),  # checked before the fits
        seed=args.seed,
        trials=args.trials,
        methods=tuple(args.methods or METHODS),
        coverage=not args.no_coverage,
        min_data_share=args.data_share,
        cover_radius=args.cover_radius,
    )


def cmd_tokenizer_extend(args: argparse.Namespace) -> dict[str, Any]:
    from pathlib import Path

    from trajeglish_env.checkpoint import load_checkpoint, load_pretrained, pretrained_path, save_checkpoint
    from trajeglish_env.checkpoint_reading import drawn_base, reading_extension
    from trajeglish_env.tokenizer.extend import extend_vocabulary, extension_report
    from trajeglish_env.tokenizer.fit import evaluate_vocabulary_file
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

    assets = pretrained_path().parent.resolve()
    for flag, path, example in (
        ("--out", args.out, "vocab.npz"),
        ("--reading-out", args.reading_out, "model.pt"),
    ):
        if path is None:
            continue
        output_file(path, flag, example)
        if Path(path).resolve().parent == assets:  # the docs' old example rewrote the shipped model
            raise ValueError(
                f"{flag} {path}: refusing to write into the package's shipped assets ({assets}); write it "
                "elsewhere (to ship it, copy it there on purpose)"
            )
        if args.base != "shipped" and Path(path).resolve() == Path(args.base).resolve():
            raise ValueError(f"{flag} {path}: that is --base itself; write the extension to another file")
    model = None  # the checkpoint to extend, drawn tokens only (a reading extension's base)
    if args.base == "shipped":
        model = drawn_base(load_pretrained())
    elif Path(args.base).suffix == ".npz":
        if args.reading_out:
            raise ValueError(f"--reading-out needs --base to be a checkpoint, not the vocabulary {args.base}")
        base = MotionVocabulary.load(args.base)
    else:
        model = drawn_base(load_checkpoint(args.base))
    base = model.vocabulary if model is not None else base
    if args.size <= base.size:
        raise ValueError(f"--size {args.size}: an extension needs more than the base's {base.size} templates")
    vocab = extend_vocabulary(base, args.size, args.cover_radius)
    out = vocab.save(args.out)
    result: dict[str, Any] = {"out": str(out), "extension": extension_report(vocab)}
    if args.reading_out and model is not None:
        reading = reading_extension(model, vocab)
        result["reading_out"] = str(
            save_checkpoint(args.reading_out, reading.model, reading.vocabulary, reading.training)
        )
    if args.data:
        result["heldout"] = {
            name: evaluate_vocabulary_file(v, args.data, collisions=False)
            for name, v in (("base", base), ("extended", vocab))
        }
    return result


def add_tokenizer_commands(add: AddCommand, sub: Any) -> None:
    """Register ``tokenizer fit``, ``tokenizer eval`` and ``tokenizer extend`` with the parser's ``add``."""
    tok = sub.add_parser("tokenizer", help="fit, evaluate and extend motion-token vocabularies")
    tsub = tok.add_subparsers(dest="tokenizer_command", required=True)
    p = add(
        "fit", cmd_tokenizer_fit, "fit k-disks vocabularies (one per agent class) on a scene directory", tsub
    )
    p.add_argument("--data", nargs="+", required=True, help="scene directories")
    p.add_argument("--vocab", type=int, default=384, choices=VOCAB_SIZES)
    p.add_argument("--out", required=True, help="output vocabulary file")
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument(
        "--trials", type=POSITIVE, default=8, help="k-disks trials (the best on held-out data is kept)"
    )
    no_cov = "do not reserve templates covering each class's motion envelope (40 m/s, reversing, tight turns)"
    p.add_argument("--no-coverage", action="store_true", help=no_cov)
    add_cover_args(p)
    p = add("eval", cmd_tokenizer_eval, "discretization error of k-disks and the baselines", tsub)
    p.add_argument("--data", nargs="+", required=True, help="held-out scenes to evaluate on")
    p.add_argument(
        "--fit-data", nargs="+", help="scenes to fit the vocabularies on (default: a split of --data)"
    )
    p.add_argument("--trials", type=POSITIVE, default=4)
    p.add_argument(
        "--vocab", type=int, nargs="*", choices=VOCAB_SIZES, help="default: the paper's 128 256 384 512"
    )
    p.add_argument("--out", default="out/tokenizer_eval", help="directory for plots")
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument(
        "--methods", nargs="*", choices=("xyh-grid", "xy-grid", "k-means", "k-disks"), help="default: all"
    )
    p.add_argument("--no-coverage", action="store_true", help=no_cov)
    add_cover_args(p)
    p = add(
        "extend",
        cmd_tokenizer_extend,
        "append envelope-covering templates to a trained model's vocabulary (old token ids unchanged), "
        "for a fine-tune with train --init CKPT --vocab OUT",
        tsub,
    )
    p.add_argument("--base", default="shipped", help="'shipped', a checkpoint or a vocabulary file (.npz)")
    p.add_argument(
        "--size",
        type=POSITIVE,
        default=2048,
        help="templates per class after the extension (default 2048: every motion of the env's limits, "
        "the continuous action's kinematic bicycle included, within 5 cm)",
    )
    p.add_argument(
        "--cover-radius",
        type=positive_float,
        default=VEHICLE_COVER_RADIUS,
        help=f"metres within which the vehicle cover reaches every envelope transition "
        f"(default {VEHICLE_COVER_RADIUS}: every envelope track within 5 cm)",
    )
    p.add_argument("--out", required=True, help="output vocabulary file (.npz)")
    p.add_argument(
        "--reading-out",
        help="also write the base checkpoint reading the extension (ego, logged and external agents tracked "
        "within 5 cm) while it draws its own tokens with the same logits (checkpoint_reading)",
    )
    p.add_argument(
        "--data", nargs="+", help="held-out scenes: the base's and the extension's errors on their tracks"
    )
