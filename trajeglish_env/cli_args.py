"""Argument types and checks of the ``trajeglish`` command line: bad input is one line on stderr and
exit code 2 (argparse types for counts, rates and probabilities; output directories; scene indices)."""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

from trajeglish_env.model.config import MAP_SELECT
from trajeglish_env.sampler.config import CACHE_DTYPES, COMPUTE_DTYPES
from trajeglish_env.training.precision import PRECISIONS

# Errors that mean bad input (a wrong value, a missing, corrupt or misplaced file): one line on stderr and
# exit code 2. ScenarioError, CheckpointError, WomdFormatError, UnknownSceneError and the validation errors
# of the library are ValueErrors. Anything else is a bug and keeps its traceback.
USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,
    FileNotFoundError,
    FileExistsError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
)
EXIT_BAD_INPUT = 2


class UsageError(SystemExit):
    """A bad command line, already reported on stderr: exit code 2; ``message`` for ``--json`` output."""

    def __init__(self, message: str):
        super().__init__(EXIT_BAD_INPUT)
        self.message = message


class ArgParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr (``prog: error: ...``), exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Report a bad command line in one line, without the usage block."""
        text = one_line(message)
        sys.stderr.write(f"{self.prog}: error: {text}\n")
        raise UsageError(text)


def one_line(message: str) -> str:
    """``message`` with its lines joined, so that an error is always a single line."""
    return " ".join(line.strip() for line in message.splitlines() if line.strip())


def integer_at_least(low: int) -> Callable[[str], int]:
    """Argument type: an integer >= ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
        return value

    return parse


def auto_or_at_least(low: int) -> Callable[[str], int | str]:
    """Argument type: ``auto`` or an integer >= ``low``."""
    count = integer_at_least(low)

    def parse(text: str) -> int | str:
        if text == "auto":
            return text
        try:
            return count(text)
        except argparse.ArgumentTypeError:
            message = f"expected 'auto' or an integer >= {low}, got {text!r}"
            raise argparse.ArgumentTypeError(message) from None

    return parse


def _float_where(text: str, ok: Callable[[float], bool], expected: str) -> float:
    """``text`` as a number that satisfies ``ok`` (NaN never does), else an argparse error naming it."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if math.isnan(value) or not ok(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """Argument type: a finite number > 0."""
    return _float_where(text, lambda v: math.isfinite(v) and v > 0, "a finite number > 0")


def non_negative_float(text: str) -> float:
    """Argument type: a finite number >= 0 (a weight that may be off)."""
    return _float_where(text, lambda v: math.isfinite(v) and v >= 0, "a finite number >= 0")


def at_least_one(text: str) -> float:
    """Argument type: a finite number >= 1 (a loss weight)."""
    return _float_where(text, lambda v: math.isfinite(v) and v >= 1, "a finite number >= 1")


def below_one(text: str) -> float:
    """Argument type: a number in [0, 1) (a share that leaves something)."""
    return _float_where(text, lambda v: 0 <= v < 1, "a number in [0, 1)")


def probability(text: str) -> float:
    """Argument type: a number in (0, 1] (nucleus sampling's top-p)."""
    return _float_where(text, lambda v: 0 < v <= 1, "a number in (0, 1]")


def unit_float(text: str) -> float:
    """Argument type: a number in [0, 1] (a share)."""
    return _float_where(text, lambda v: 0 <= v <= 1, "a number in [0, 1]")


POSITIVE = integer_at_least(1)
NON_NEGATIVE = integer_at_least(0)


def _no_file_above(out: Path, option: str) -> None:
    """The nearest existing folder above ``out`` must be a folder (not a file the output would go under)."""
    above = next((p for p in out.absolute().parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise NotADirectoryError(f"{option} {out}: {above} is a file, not a directory")


def output_dir(path: str, option: str = "--out") -> Path:
    """An output directory: it may not exist yet, but it may not be a file (nor lie under one)."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{option} {out}: exists and is not a directory")
    _no_file_above(out, option)
    return out


def output_file(path: str, option: str, example: str) -> Path:
    """An output file, checked before any work: it may not be a directory (``example``: a file name to
    suggest in it) nor lie under a file."""
    out = Path(path)
    if out.is_dir():
        raise IsADirectoryError(
            f"{option} {out}: is a directory; expected a file to write, e.g. {out / example}"
        )
    _no_file_above(out, option)
    return out


def scene_at(path: str, index: int) -> Any:
    """Scene ``index`` of a scenario file; an index past its end names the option and the file."""
    from trajeglish_env.scenario_io import load_scenarios

    scenes = load_scenarios(path)
    if index >= len(scenes):
        raise ValueError(
            f"--index {index}: {path} holds {len(scenes)} scene(s) (indices 0..{len(scenes) - 1})"
        )
    return scenes[index]


def add_dtype_args(p: argparse.ArgumentParser) -> None:
    """The precision options of a command that samples a model: its cache and its linear layers."""
    p.add_argument("--cache-dtype", choices=CACHE_DTYPES, default="bfloat16", help="decoder cache dtype")
    p.add_argument(
        "--compute-dtype",
        choices=COMPUTE_DTYPES,
        default="auto",
        help="dtype the linear layers multiply in (auto: bfloat16 for batches of 2 rows or more where the "
        "CPU has it natively)",
    )


def add_cover_args(p: argparse.ArgumentParser) -> None:
    """The motion-envelope cover's options of ``tokenizer fit`` and ``tokenizer eval``."""
    from trajeglish_env.tokenizer.fit import MIN_DATA_SHARE

    p.add_argument(
        "--data-share",
        type=probability,
        default=MIN_DATA_SHARE,
        help=f"share of V kept for templates sampled from data (default {MIN_DATA_SHARE}); a cover that "
        "leaves less is made at a wider radius",
    )
    p.add_argument(
        "--cover-radius",
        type=positive_float,
        help="metres within which the vehicle cover reaches every envelope transition (default 0.045; "
        "0.03 with --vocab 1024 --data-share 0.2 keeps envelope tracks within 5 cm)",
    )


def add_budget_and_mix_args(p: argparse.ArgumentParser) -> None:
    """``train``'s wall-clock budget and data-mix options."""
    p.add_argument(
        "--minutes",
        type=positive_float,
        help="wall-clock budget: no step after M minutes; the last step is checkpointed (--resume goes on)",
    )
    p.add_argument(
        "--fit-steps",
        action="store_true",
        help="with --minutes: the step rate sets the schedule's length (first over a tenth of the budget, "
        "then refitted after every step), so the learning rate decays to 0 as the budget ends (--steps is "
        "the most)",
    )
    p.add_argument(
        "--repeat",
        nargs="+",
        default=[],
        metavar="KIND=N",
        help="draw the training scenes of a kind (highway/roundabout) or source (sumo) N times an epoch",
    )
    p.add_argument(
        "--noise-on-device",
        action="store_true",
        help="draw the noisy input tokens in the training process on the model's device (a GPU) instead of "
        "in the loading processes: the same draws up to rounding, a fraction of the loaders' work",
    )
    p.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="auto",
        help="a step's arithmetic on CPU: 'auto' (bfloat16 autocast where the CPU multiplies bfloat16 "
        "natively and the model is at least 64 wide, float32 elsewhere), 'float32' or 'bfloat16'; CUDA "
        "always autocasts to bfloat16",
    )


def add_map_args(p: argparse.ArgumentParser) -> None:
    """``train``'s choices of what a window shows of the map (inputs, not weights: an ``--init``
    checkpoint may be fine-tuned with other ones)."""
    p.add_argument(
        "--map-select",
        choices=MAP_SELECT,
        help="map chunks of a window: nearest its frame agent ('frame', the default) "
        "or nearest any of its agents ('agents': every agent sees the road near it), or nearest any of "
        "them and where each would be 0.8 / 1.6 / 2.4 s on at its speed and turn rate ('ahead': the road "
        "the agents drive onto); with --init, the checkpoint's",
    )
    p.add_argument(
        "--map-stride",
        type=integer_at_least(1),
        help="a map chunk takes every Nth point of its polyline (ModelConfig.map_stride; 1, the default and "
        "the shipped model's: 20 points 0.5 m apart; 4: chunks 38 m long); with --init, the checkpoint's",
    )


def with_map_args(config: Any, args: argparse.Namespace) -> Any:
    """A ModelConfig with the ``--map-select`` / ``--map-stride`` that were given."""
    import dataclasses

    if args.map_select is not None:
        config = dataclasses.replace(config, map_select=args.map_select)
    if args.map_stride is not None:
        config = dataclasses.replace(config, map_stride=args.map_stride)
    return config


EXIT_INTERRUPTED = 130  # the shell's code for a process ended by Ctrl-C


@contextlib.contextmanager
def interrupt_on_sigterm() -> Iterator[None]:
    """SIGTERM (``kill``, a job scheduler) stops a command as Ctrl-C does, so that its cleanup runs (in
    the main thread only; elsewhere signals cannot be handled)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interrupted_note(args: argparse.Namespace) -> str:
    """What an interrupted command left: whole files, and for ``train`` the step its resume goes on from."""
    note = (
        "the files already written are whole (atomic writes), and generate, convert-womd, train --resume, "
        "export-submission and scorecard go on from them"
    )
    if args.command_name.split()[-1] == "train" and getattr(args, "out", None):  # "trajeglish train"
        from trajeglish_env.training.run_records import resume_point

        step = resume_point(Path(args.out))
        note += (
            f"; train --resume goes on from step {step} ({Path(args.out) / 'last.pt'}; the steps since are "
            "taken again, --checkpoint-every N to lose fewer)"
            if step is not None
            else "; no checkpoint was written yet, so run train again without --resume (a new run)"
        )
    return note
