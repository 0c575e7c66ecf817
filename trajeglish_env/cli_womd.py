"""The ``trajeglish`` commands of the WOMD-to-leaderboard workflow (``export-submission``,
``score-submission``), registered by
:func:`trajeglish_env.cli.build_parser`; each runs alone or under ``torchrun`` (ranks share the work and
the main rank prints the merged result)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from trajeglish_env.cli_args import (
    NON_NEGATIVE,
    POSITIVE,
    add_dtype_args,
    output_dir,
    positive_float,
    probability,
)
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE

Handler = Callable[[argparse.Namespace], dict[str, Any]]
AddCommand = Callable[..., argparse.ArgumentParser]  # build_parser's add(name, handler, help_text)


def cmd_export_submission(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
    from trajeglish_env.distributed import init_ranks, rank_device
    from trajeglish_env.metrics.submission_metadata import SubmissionMetadata, format_parameter_count
    from trajeglish_env.metrics.submission_scores import WOSAC_ROLLOUTS
    from trajeglish_env.sampler.config import SamplingConfig
    from trajeglish_env.sampler.rollouts import auto_processes
    from trajeglish_env.submission_export import WOSAC_STEPS, ExportConfig, export_submission

    device = rank_device()
    ranks = init_ranks(device)
    ckpt = load_checkpoint(args.ckpt, device) if args.ckpt else load_pretrained(device)
    count = sum(p.numel() for p in ckpt.model.parameters())
    metadata = SubmissionMetadata(
        account_name=args.account_name or "",
        unique_method_name=args.method_name or "",
        authors=tuple(args.authors or ()),
        affiliation=args.affiliation or "",
        description=args.description or "",
        method_link=args.method_link or "",
        uses_lidar_data=args.uses_lidar_data,
        uses_camera_data=args.uses_camera_data,
        uses_public_model_pretraining=args.uses_public_model_pretraining,
        public_model_names=tuple(args.public_model_names or ()),
        num_model_parameters=args.num_model_parameters or format_parameter_count(count),
        acknowledge_complies_with_closed_loop_requirement=True,  # the sampler is closed-loop at 10 Hz
    )
    sampling = SamplingConfig(
        args.temperature, args.top_p, args.cache_dtype, compute_dtype=args.compute_dtype
    )
    # one process per free core (looked at once), unless torchrun ranks share the machine's cores already
    processes = args.processes or (auto_processes(args.rollouts) if ranks.world == 1 else 1)
    config = ExportConfig(args.rollouts, args.steps, sampling, args.seed, args.prefix, processes)
    if args.steps != WOSAC_STEPS and ranks.main:  # allowed (a quick try of the pipeline), never silently
        print(
            f"export-submission: warning: --steps {args.steps}: WOSAC and score-submission need "
            f"{WOSAC_STEPS} steps after the current one; this submission cannot be scored",
            file=sys.stderr,
        )
    if args.rollouts != WOSAC_ROLLOUTS and ranks.main:
        print(
            f"export-submission: warning: --rollouts {args.rollouts}: WOSAC takes exactly {WOSAC_ROLLOUTS} "
            "joint rollouts per scenario; the leaderboard would reject this submission",
            file=sys.stderr,
        )
    result = export_submission(
        args.data, ckpt, output_dir(args.out), metadata, config, not args.quiet and ranks.main, ranks
    )
    result.update(device=str(device), _silent=not ranks.main)
    return result


def cmd_score_submission(args: argparse.Namespace) -> dict[str, Any]:
    from trajeglish_env.distributed import init_ranks
    from trajeglish_env.metrics.submission_scores import score_submission

    ranks = init_ranks()
    result = score_submission(
        args.submission, args.data, args.metrics, args.out, not args.quiet and ranks.main, ranks
    )
    result["_silent"] = not ranks.main
    return result


def add_womd_commands(add: AddCommand) -> None:
    """Register the workflow's commands with the parser's ``add``."""
    p = add(
        "export-submission",
        cmd_export_submission,
        "closed-loop rollouts of every scenario -> Waymo Sim Agents submission shards and a .tar.gz "
        "(torchrun: scenarios split over ranks)",
    )
    p.add_argument("--data", nargs="+", required=True, help="converted scenario shards (convert-womd)")
    p.add_argument("--out", required=True, help="output directory (resumes an interrupted export)")
    p.add_argument("--ckpt", help="checkpoint (default: the shipped model)")
    p.add_argument("--rollouts", type=POSITIVE, default=32, help="joint rollouts per scenario (WOSAC: 32)")
    p.add_argument(
        "--steps", type=POSITIVE, default=80, help="simulated steps after the current one (WOSAC: 80)"
    )
    p.add_argument("--temperature", type=positive_float, default=DEFAULT_TEMPERATURE)
    p.add_argument("--top-p", type=probability, default=1.0)
    add_dtype_args(p)
    p.add_argument(
        "--seed", type=NON_NEGATIVE, default=0, help="each scenario's seed derives from this and its id"
    )
    p.add_argument(
        "--processes",
        type=POSITIVE,
        help="processes each scenario's rollouts are split over, the same rollouts (default: one per core "
        "other processes leave free; 1 under torchrun)",
    )
    p.add_argument("--prefix", default="submission", help="file names: PREFIX.binproto-K-of-N, PREFIX.tar.gz")
    p.add_argument("--account-name", help="e-mail registered at waymo.com/open (required)")
    p.add_argument("--method-name", help="unique method name shown on the leaderboard (required)")
    p.add_argument("--authors", nargs="+", help="author names (required)")
    p.add_argument("--affiliation", help="(required)")
    p.add_argument("--description", help="a brief description of the method (required)")
    p.add_argument("--method-link", help="link to a paper or page describing the method")
    p.add_argument("--uses-lidar-data", action="store_true", help="the model uses WOMD lidar data")
    p.add_argument("--uses-camera-data", action="store_true", help="the model uses WOMD camera data")
    p.add_argument(
        "--uses-public-model-pretraining", action="store_true", help="pretrained from a public LLM/VLM"
    )
    p.add_argument("--public-model-names", nargs="+", help="names of those public models")
    p.add_argument("--num-model-parameters", help="e.g. 200K, 3M (default: counted from the checkpoint)")

    p = add(
        "score-submission",
        cmd_score_submission,
        "WOSAC realism scores of a submission (shard, .tar.gz or directory) against converted shards "
        "(torchrun: scenarios split over ranks)",
    )
    p.add_argument("submission", help="a .binproto shard, a .tar.gz of shards or a directory of shards")
    p.add_argument("--data", nargs="+", required=True, help="the converted scenario shards (convert-womd)")
    p.add_argument(
        "--metrics",
        choices=("2024", "2024-era", "2025"),
        default="2025",
        help="WOSAC config: 2025, 2024 (its weights under the current official code), or 2024-era (as "
        "the 2024 leaderboard scored: time to collision of every evaluated object, not vehicles only)",
    )
    p.add_argument("--out", help="also write every scenario's scores to this JSON file")
