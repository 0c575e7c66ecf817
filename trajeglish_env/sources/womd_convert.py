"""``trajeglish convert-womd``: WOMD TFRecords -> scenario shards (+ raw log details), at dataset scale.

One input file -> ``NAME.scn.npz`` (the scenes) and ``NAME.details.npz`` (their raw log values, see
:mod:`trajeglish_env.metrics.log_details_io`), both written atomically. Files are split over the ranks of
a ``torchrun`` job (every ``world``-th file) and, within a rank, over ``workers`` processes; every shard
depends only on its input, so any split writes the same files and the merged report is the one-process
report. Resumable: an input whose shard and details both load is skipped. A corrupt input does not stop
the run; it is reported under ``failed`` and nothing is written for it.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from tqdm import tqdm

from trajeglish_env.distributed import Ranks, gather, my_share
from trajeglish_env.metrics.log_details_io import details_path, load_log_details, save_log_details
from trajeglish_env.metrics.womd_details import parse_womd_details
from trajeglish_env.scenario_io import load_scenarios, save_scenarios
from trajeglish_env.sources.womd import good_records, output_name, parse_scenario
from trajeglish_env.sources.womd_tfrecord import WomdFormatError

__all__ = ["check_inputs", "convert_file", "convert_womd"]


def _existing_scenes(target: Path) -> int | None:
    """Scenes of an already converted input (shard and details both load and agree); else None."""
    if not (target.is_file() and details_path(target).is_file()):
        return None
    try:
        scenes, details = load_scenarios(target), load_log_details(details_path(target))
    except (ValueError, OSError):
        return None
    return len(scenes) if len(scenes) == len(details) else None


def convert_file(path: str, target: str) -> dict[str, Any]:
    """Convert one TFRecord file; returns ``{"status": converted|skipped|failed, "scenes", "error",
    "bad_tail"}`` (``bad_tail``: what was kept of a file whose good records end in a truncated or corrupt
    tail, with the warning line)."""
    out = Path(target)
    existing = _existing_scenes(out)
    if existing is not None:
        return {"status": "skipped", "scenes": existing}
    try:
        records, tail = good_records(path)
        if not records:
            raise WomdFormatError(f"{path}: no records (empty file)")
        scenes, details = [], []
        for index, data in records:
            origin = f"{path}: record {index}"
            scenes.append(parse_scenario(data, origin=origin))
            details.append(parse_womd_details(data, origin=origin))
        save_log_details(details_path(out), details)
        save_scenarios(out, scenes)
    except (ValueError, OSError) as exc:  # WomdFormatError, ScenarioError, unreadable file
        return {"status": "failed", "scenes": 0, "error": str(exc)}
    result: dict[str, Any] = {"status": "converted", "scenes": len(scenes)}
    if tail is not None:
        result["bad_tail"] = {
            "entry": {
                "file": path,
                "records_kept": len(scenes),
                "byte_offset": tail.offset,
                "error": str(tail),
            },
            "warning": f"{tail.path}: kept {len(scenes)} good record(s); ignored the rest of the file from "
            f"byte offset {tail.offset} (record {tail.record}: {tail.problem})",
        }
    return result


def check_inputs(paths: Sequence[Path]) -> None:
    """Every input must be an existing, non-empty regular file (a TFRecord holds at least one record)."""
    for path in paths:
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such WOMD TFRecord file")
        if not path.is_file():
            raise WomdFormatError(f"{path}: not a regular file (expected a WOMD TFRecord file)")
        if path.stat().st_size == 0:
            raise WomdFormatError(f"{path}: empty file (a WOMD TFRecord file holds at least one record)")


def _results(jobs: list[tuple[str, str]], workers: int) -> Iterator[dict[str, Any]]:
    """Results of ``convert_file`` over ``jobs`` in order, in ``workers`` processes when > 1."""
    if workers <= 1 or len(jobs) <= 1:
        yield from (convert_file(*job) for job in jobs)
        return
    context = multiprocessing.get_context("spawn")  # no fork of a process that may hold torch threads
    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=context) as pool:
        yield from pool.map(convert_file, *zip(*jobs, strict=True))


def convert_womd(
    files: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    progress: bool = True,
    workers: int = 1,
    ranks: Ranks | None = None,
) -> dict[str, Any]:
    """Convert WOMD TFRecord files to scenario shards in ``out`` (see the module docstring).

    Every input must be an existing, non-empty file (checked before anything is converted). A file whose
    good records are followed by a truncated or corrupt tail (an interrupted copy) keeps its good records;
    the tail is listed under ``bad_tails`` and reported on stderr. Returns (on every rank, merged over
    ranks) ``{"converted", "skipped", "failed", "bad_tails", "outputs", "scenes", "scenes_skipped",
    "processes", "workers", "seconds"}``; lists are in input order.
    """
    start = time.perf_counter()
    ranks = ranks or Ranks()
    out = Path(out)
    paths = [Path(f) for f in files]
    names: dict[str, Path] = {}
    for path in paths:
        other = names.setdefault(output_name(path), path)
        if other != path:
            raise ValueError(f"{other} and {path} would both be written to {out / output_name(path)}")
    check_inputs(paths)
    mine = my_share(list(range(len(paths))), ranks)
    jobs = [(str(paths[i]), str(out / output_name(paths[i]))) for i in mine]
    bar = tqdm(total=len(jobs), desc="convert-womd", unit="file", file=sys.stderr, disable=not progress)
    done: list[tuple[int, dict[str, Any]]] = []
    for i, result in zip(mine, _results(jobs, workers), strict=True):
        done.append((i, result))
        if "bad_tail" in result:
            bar.write(f"convert-womd: warning: {result['bad_tail']['warning']}", file=sys.stderr)
        bar.update(1)
        bar.set_postfix(scenes=sum(r["scenes"] for _, r in done))
    bar.close()
    merged = sorted((item for part in gather(done, ranks) for item in part), key=lambda item: item[0])
    report: dict[str, Any] = {"converted": [], "skipped": [], "failed": [], "bad_tails": [], "outputs": []}
    report.update(scenes=0, scenes_skipped=0)
    for i, result in merged:
        name = str(paths[i])
        if result["status"] == "failed":
            report["failed"].append({"file": name, "error": result["error"]})
        elif result["status"] == "skipped":
            report["skipped"].append(name)
            report["scenes_skipped"] += result["scenes"]
        else:
            if "bad_tail" in result:
                report["bad_tails"].append(result["bad_tail"]["entry"])
            report["converted"].append(name)
            report["outputs"].append(str(out / output_name(paths[i])))
            report["scenes"] += result["scenes"]
    report.update(processes=ranks.world, workers=workers, seconds=time.perf_counter() - start)
    return report
