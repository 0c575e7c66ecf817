"""Helpers of ``scripts/device_train.sh``, the one-call training job for a lent GPU machine.

``python trajeglish_env/device_job.py check|resume|pack ...`` (as a file: ``check`` runs before the
packages that ``import trajeglish_env`` needs are known to be there):

- ``check``: print the machine (Python, torch, CUDA, GPU, cores) and fail with one clear line when the job
  cannot run there (no CUDA where it is required, a package missing: which wheel to carry). Prints
  ``KEY=VALUE`` lines on stdout for the script (``SUMO_OK``, ``CORES``).
- ``saved RUN_IN``: a carried run's settings as ``SAVED_NAME=VALUE`` lines (plain JSON, read at once).
- ``check ... --resume RUN_IN RUN`` also rebuilds ``RUN/last.pt`` from the carried folder (``last.pt`` or
  its parts ``last.pt.000``, ``last.pt.001``, ... as ``pack`` wrote them) and checks that it loads.
- ``extension FILE INIT SIZE``: whether a carried vocabulary ``FILE`` (``make device-vocab``) extends the
  vocabulary of ``INIT`` (``shipped`` or a checkpoint) to ``SIZE`` tokens per class, so the job trains on
  it instead of extending there (about half a minute of the call); exit 1 with the reason when it does not.
- ``pack RUN OUT``: write the checkpoint, a small ``summary.json`` (held-out NLL, training curve, one
  record per call) and the log into ``OUT`` within the device tool's limits on what comes back (at most 8
  files of at most 16 MiB, 64 MiB together); ``OUT/resume/`` is what the next call carries as ``RUN_IN``.

Nothing here needs a GPU; the project builds and tests without one.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import shlex
import shutil
import sys
from pathlib import Path
from typing import Any

MAX_FILES = 8  # the device tool brings back at most 8 files,
MAX_FILE_BYTES = 16 * 2**20  # each at most 16 MiB,
MAX_TOTAL_BYTES = 64 * 2**20  # 64 MiB together
PART_BYTES = 15 * 2**20  # large files travel in parts of this size
RUN_RECORD = "run.json"
CURVE_POINTS = 200  # training-curve rows kept in summary.json

# import name -> the wheel to carry (``make device-wheels`` downloads them into .whl/)
NEEDED = {
    "gymnasium": "gymnasium",
    "farama_notifications": "farama-notifications",
    "pettingzoo": "pettingzoo",
    "pygame": "pygame-ce",
    "highway_env": "highway-env",
    "numpy": "numpy",
    "torch": "torch",
    "tqdm": "tqdm",
    "matplotlib": "matplotlib",
    "pandas": "pandas",
    "cloudpickle": "cloudpickle",
}
# settings that fix a run's model and schedule: a resumed call must keep them (train refuses otherwise)
SAVED = (
    "PRESET",
    "STEPS",
    "BATCH",
    "LR",
    "WARMUP",
    "SEED",
    "VAL_EVERY",
    "CKPT_EVERY",
    "SIGNAL_INPUT",
    "SIGNAL_LR_SCALE",
    "NEIGHBOUR_INPUT",
    "LANE_INPUT",
    "VOCAB",
    "EXTEND",
    "COVER_RADIUS",
    "DATA_SHARE",
    "MAP_SELECT",
    "MAP_STRIDE",
    "FIT_STEPS",
    "REPEAT",
    "CLOSED_LOOP",
    "INTERACTION_WEIGHT",
    "BEND_WEIGHT",
    "COLLISION_WEIGHT",
    "COLLISION_HORIZON",
    "COLLISION_ROLLED_OUT_ONLY",
    "COLLISION_SOURCES",
    "OFFROAD_WEIGHT",
    "HISTORY_DROPOUT",
)


class JobError(RuntimeError):
    """The job cannot go on; the message says why and what to do."""


def _say(*lines: str) -> None:
    for line in lines:
        print(f"device_job: {line}", file=sys.stderr)


def check(device: str, sumo: str) -> dict[str, str]:
    """Describe the machine; raise :class:`JobError` when the job cannot run on it."""
    missing = []
    for module, wheel in NEEDED.items():
        try:
            __import__(module)
        except ImportError as error:
            missing.append(f"{wheel} (import {module}: {error})")
    if missing:
        raise JobError(
            "missing Python packages: "
            + "; ".join(missing)
            + '. Run `make device-wheels` where pip reaches PyPI and carry .whl (carry: [".whl"])'
        )
    import torch

    cores = os.cpu_count() or 1
    _say(f"python {platform.python_version()} ({sys.executable}), torch {torch.__version__}, {cores} cores")
    cuda = torch.cuda.is_available()
    gpu = "none"
    if cuda:
        props = torch.cuda.get_device_properties(0)
        gpu = props.name
        _say(
            f"CUDA {torch.version.cuda}: {torch.cuda.device_count()} x {props.name}, "
            f"{props.total_memory / 2**30:.0f} GiB, capability {props.major}.{props.minor}"
        )
    if device == "cuda":
        if not cuda:
            raise JobError(
                f"DEVICE=cuda but torch {torch.__version__} sees no CUDA device "
                f"(built for CUDA {torch.version.cuda}); run on the GPU machine, or DEVICE=cpu for a dry run"
            )
        x = torch.randn(256, 256, device="cuda", dtype=torch.bfloat16)
        float((x @ x).float().sum())  # the GPU computes
    import trajeglish_env  # noqa: F401  (registers the envs: gymnasium and pettingzoo import cleanly)
    import trajeglish_env.sources.highway  # noqa: F401  (highway-env and pygame import cleanly)

    sumo_ok = _sumo_available()
    if sumo not in ("auto", "0") and not sumo_ok:
        raise JobError(
            f"SUMO_SCENES={sumo} but Eclipse SUMO is not on this machine; its wheel (eclipse-sumo, about "
            "150 MB) is too big to carry: generate SUMO scenes where SUMO is installed "
            '(`make device-sumo-scenes`) and carry them (DATA_IN=.devdata, carry: [".devdata"]), '
            "or set SUMO_SCENES=0"
        )
    return {
        "SUMO_OK": str(int(sumo_ok)),
        "CORES": str(cores),
        "GPU": gpu if device == "cuda" else "none (DEVICE=cpu)",
        "TORCH": str(torch.__version__),
        "PY_VERSION": platform.python_version(),
    }


def _sumo_available() -> bool:
    from trajeglish_env.sources.sumo_tools import SumoNotAvailableError, sumo_binary

    try:
        sumo_binary("sumo")
        sumo_binary("netgenerate")
    except SumoNotAvailableError:
        return False
    return True


def saved(run_in: Path) -> dict[str, str]:
    """The settings a carried run was started with (``SAVED_NAME``) and this call's number (``CALL``);
    plain JSON, no torch: read before anything slow, so that a conflicting setting fails at once."""
    if not run_in.is_dir():
        raise JobError(f'RUN_IN={run_in}: no such folder (carry it, e.g. carry: [".devrun"])')
    record = _read_record(run_in)
    values = {f"SAVED_{k}": str(v) for k, v in record.get("params", {}).items() if k in SAVED}
    return {**values, "CALL": str(len(record.get("calls", [])))}


def resume(run_in: Path, run: Path) -> dict[str, str]:
    """Rebuild ``run/last.pt`` from ``run_in``; return the run's saved settings and its step."""
    from trajeglish_env.checkpoint import CheckpointError, TrainerState, load_checkpoint
    from trajeglish_env.scenario_io import atomic_path

    values = saved(run_in)
    run.mkdir(parents=True, exist_ok=True)
    parts = sorted(run_in.glob("last.pt.[0-9][0-9][0-9]"))
    if (run_in / "last.pt").is_file():
        with atomic_path(run / "last.pt") as tmp:
            shutil.copyfile(run_in / "last.pt", tmp)
    elif parts:
        if [p.name for p in parts] != [f"last.pt.{i:03d}" for i in range(len(parts))]:
            raise JobError(f"RUN_IN={run_in}: parts {[p.name for p in parts]} are not a complete series")
        with atomic_path(run / "last.pt") as tmp, open(tmp, "wb") as dst:
            for part in parts:
                with open(part, "rb") as src:
                    shutil.copyfileobj(src, dst)
    else:
        raise JobError(f"RUN_IN={run_in} holds neither last.pt nor last.pt.000...: nothing to resume")
    try:
        ckpt = load_checkpoint(run / "last.pt")
    except CheckpointError as error:
        raise JobError(f"RUN_IN={run_in}: the rebuilt last.pt does not load: {error}") from error
    try:
        state = TrainerState.of(ckpt)
    except CheckpointError as error:
        raise JobError(f"RUN_IN={run_in}: the rebuilt last.pt is no run to resume: {error}") from error
    step, total = state.step, int(state.train_config.get("steps", 0))
    if total and step >= total:  # a whole call spent on generation and no step: say so before anything
        raise JobError(
            f"RUN_IN={run_in}: the run finished its schedule (step {step} of {total}; with FIT_STEPS=1, the "
            "default, the first call fits the whole schedule to its own budget): nothing left to train. "
            "Start a new run without RUN_IN (INIT=<its model.pt> to train on from it), or give a first call "
            "FIT_STEPS=0 to spread STEPS over calls"
        )
    record = _read_record(run_in)
    if record:
        _write_json(run / RUN_RECORD, record)
    _say(f"resuming {run_in} at step {step} ({values['CALL']} earlier calls)")
    return {**values, "RESUME_STEP": str(step)}


def _write_json(path: Path, value: dict[str, Any]) -> None:
    """Write ``value`` to ``path`` atomically (a killed call leaves the previous file whole)."""
    from trajeglish_env.scenario_io import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(value, indent=2))


def _read_record(folder: Path) -> dict[str, Any]:
    path = folder / RUN_RECORD
    return json.loads(path.read_text()) if path.is_file() else {}


def _number(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def _curve(run: Path) -> list[dict[str, float]]:
    """The run's metrics rows: every validation row, and loss rows thinned to about CURVE_POINTS."""
    path = run / "metrics.csv"
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        rows = [{k: float(v) for k, v in r.items() if v not in ("", None)} for r in csv.DictReader(fh)]
    every = max(1, math.ceil(len(rows) / CURVE_POINTS))
    keep = [r for i, r in enumerate(rows) if "val_nll" in r or i % every == 0 or i == len(rows) - 1]
    return [
        {k: int(v) if k == "step" else round(v, 5) for k, v in r.items() if k in ("step", "loss", "val_nll")}
        for r in keep
    ]


def pack(run: Path, out: Path, facts: dict[str, Any], log: Path | None) -> dict[str, Any]:
    """Write what comes back from the device into ``out``; returns the summary."""
    record = _read_record(run)
    record.setdefault("params", {}).update(facts.pop("params", {}))
    train = facts.get("train", {})
    summary: dict[str, Any] = {"format": "trajeglish_env.device_run", "version": 1}
    if (run / "model.pt").is_file() or (run / "last.pt").is_file():
        from trajeglish_env.checkpoint import load_checkpoint

        ckpt = load_checkpoint(run / ("model.pt" if (run / "model.pt").is_file() else "last.pt"))
        info = ckpt.training
        summary.update(
            step=info.get("step"),
            steps_total=info.get("train_config", {}).get("steps"),
            val_nll=info.get("val_nll"),
            train_loss=train.get("train_loss"),
            parameters=sum(p.numel() for p in ckpt.model.parameters()),
            train_scenes=info.get("train_scenes"),
            val_scenes=info.get("val_scenes"),
            sources=info.get("sources"),
        )
        facts.update(train_scenes=info.get("train_scenes"), val_scenes=info.get("val_scenes"))
        done = summary["steps_total"] is not None and summary["step"] >= summary["steps_total"]
        summary["finished"] = done
        per_call = int(train.get("steps", 0)) - int(train.get("resumed_from", 0))
        if not done and per_call > 0:
            summary["calls_left_at_this_pace"] = math.ceil(
                (summary["steps_total"] - summary["step"]) / per_call
            )
    record.setdefault("calls", []).append(facts)
    summary.update(params=record["params"], calls=record["calls"], curve=_curve(run))
    run.mkdir(parents=True, exist_ok=True)  # train may have failed before making it
    _write_json(run / RUN_RECORD, record)

    # what comes back, most needed first; last.pt (optimizer state too) travels in parts
    out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(out / "resume", ignore_errors=True)  # no stale part of an earlier pack
    items: list[tuple[Path, str]] = [(run / RUN_RECORD, f"resume/{RUN_RECORD}")]
    if (run / "last.pt").is_file():
        items += [(part, f"resume/{part.name}") for part in _parts(run / "last.pt", run / "parts")]
    items += [(run / "model.pt", "model.pt"), (run / "metrics.csv", "metrics.csv")]
    if log is not None:
        items.append((log, "log.txt"))
    items.append((run / "training_curve.png", "training_curve.png"))
    files, total, left = 1, 64 * 1024, []  # summary.json (written last) counts as one small file
    for src, name in items:
        if not src.is_file():
            continue
        size = src.stat().st_size
        if files + 1 > MAX_FILES or total + size > MAX_TOTAL_BYTES or size > MAX_FILE_BYTES:
            left.append(name)
            continue
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, out / name)
        files, total = files + 1, total + size
    if any(name.startswith("resume/last.pt.") for name in left):  # half a checkpoint is no checkpoint
        for part in (out / "resume").glob("last.pt.*"):
            part.unlink()
    summary["files"] = {
        str(p.relative_to(out)): p.stat().st_size for p in sorted(out.rglob("*")) if p.is_file()
    }
    if left:
        summary["left_behind"] = left
    _write_json(out / "summary.json", summary)
    if any(name.startswith("resume/") for name in left) or "model.pt" in left:
        raise JobError(
            f"{left} did not fit in what the device tool brings back ({MAX_FILES} files of "
            f"{MAX_FILE_BYTES >> 20} MiB, {MAX_TOTAL_BYTES >> 20} MiB together): use a smaller PRESET"
        )
    return summary


def _parts(path: Path, folder: Path) -> list[Path]:
    """Split ``path`` into ``folder/NAME.000``, ``.001``, ... of at most PART_BYTES each."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    parts = []
    with open(path, "rb") as src:
        while chunk := src.read(PART_BYTES):
            parts.append(folder / f"{path.name}.{len(parts):03d}")
            parts[-1].write_bytes(chunk)
    return parts


def extension(path: Path, init: str, size: int) -> str:
    """Why the vocabulary at ``path`` cannot stand for ``init``'s extended to ``size`` tokens ("" when it
    can: the base's templates, unchanged, as its first ids)."""
    from trajeglish_env.checkpoint import load_named
    from trajeglish_env.checkpoint_reading import drawn_base
    from trajeglish_env.tokenizer.extend import is_extension
    from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

    try:
        vocab = MotionVocabulary.load(path)
    except Exception as error:  # noqa: BLE001 - any unreadable file: the job extends the vocabulary itself
        return f"{path}: not a readable vocabulary ({type(error).__name__}: {error})"
    try:
        base = drawn_base(load_named(init)).vocabulary
    except Exception as error:  # noqa: BLE001 - the job's own extend then names the problem
        return f"INIT={init}: {error}"
    if vocab.size != size:
        return f"{path} holds {vocab.size} tokens per class, not {size}"
    if not is_extension(base, vocab):
        return f"{path} does not begin with {init}'s {base.size} templates"
    return ""


def _shell(values: dict[str, str]) -> None:
    for key, value in values.items():
        print(f"{key}={shlex.quote(value)}")


def main(argv: list[str] | None = None) -> int:
    # run as a file (`python trajeglish_env/device_job.py check`) so that a missing package is reported
    # here rather than by `import trajeglish_env`; the package folder then must not shadow anything
    if sys.path and Path(sys.path[0] or ".").resolve() == Path(__file__).resolve().parent:
        sys.path.pop(0)
    parser = argparse.ArgumentParser(prog="python trajeglish_env/device_job.py", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("check", help="describe the machine; fail when the job cannot run on it")
    p.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    p.add_argument("--sumo", default="auto", help="SUMO_SCENES: auto, 0, or a number (then SUMO is required)")
    p.add_argument("--resume", nargs=2, type=Path, metavar=("RUN_IN", "RUN"), help="also rebuild RUN/last.pt")
    p = sub.add_parser("saved", help="a carried run's settings (no torch)")
    p.add_argument("run_in", type=Path)
    p = sub.add_parser("extension", help="does a carried vocabulary extend INIT's to SIZE tokens?")
    p.add_argument("vocab", type=Path)
    p.add_argument("init")
    p.add_argument("size", type=int)
    p = sub.add_parser("pack", help="write what comes back into OUT")
    p.add_argument("run", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--facts", type=Path, help="KEY=VALUE lines about this call (param.NAME: a setting)")
    p.add_argument("--train-json", type=Path, help="the output of `trajeglish train --json`")
    p.add_argument("--log", type=Path)
    args = parser.parse_args(argv)
    try:
        if args.command == "check":  # one process: torch is imported once
            _shell({**check(args.device, args.sumo), **(resume(*args.resume) if args.resume else {})})
        elif args.command == "saved":
            _shell(saved(args.run_in))
        elif args.command == "extension":
            why = extension(args.vocab, args.init, args.size)
            _say(why or f"{args.vocab} extends {args.init}'s vocabulary to {args.size} tokens")
            return 1 if why else 0
        else:
            facts: dict[str, Any] = {"params": {}}
            lines = args.facts.read_text().splitlines() if args.facts and args.facts.is_file() else []
            for key, _, value in (line.partition("=") for line in lines if "=" in line):
                if key.startswith("param."):
                    facts["params"][key[6:]] = value
                else:
                    facts[key] = _number(value)
            if args.train_json and args.train_json.is_file() and args.train_json.stat().st_size:
                train = json.loads(args.train_json.read_text())
                keep = ("steps", "resumed_from", "train_loss", "val_nll", "tokens_per_second", "seconds")
                keep = (*keep, "data_wait_share", "stopped_by_time_limit")
                facts["train"] = {k: train[k] for k in keep if k in train}
                took = int(train.get("steps", 0)) - int(train.get("resumed_from", 0))
                if train.get("seconds"):
                    facts["train"]["steps_per_second"] = round(took / train["seconds"], 3)
            summary = pack(args.run, args.out, facts, args.log)
            _say(f"packed {args.out}: step {summary.get('step')}, val_nll {summary.get('val_nll')}")
            _say("files: " + ", ".join(f"{k} ({v / 2**20:.1f} MiB)" for k, v in summary["files"].items()))
    except JobError as error:
        print(f"device_train: ERROR: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
