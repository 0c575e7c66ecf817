"""``trajeglish convert-womd``: WOMD TFRecords -> scenario shards (+ raw log details), at dataset scale.

One input file -> ``NAME.scn.npz`` (the scenes) and ``NAME.details.npz`` (their raw log values, see
:mod:`trajeglish_env.metrics.log_details_io`), both written atomically. Files are split over the ranks of
a ``torchrun`` job (every ``world``-th file) and, within a rank, over ``workers`` processes; every shard
depends only on its input, so any split writes the same files and the merged report is the one-process
report. Resumable: an input whose shard and details both load and record that they were made from this
input (its size and ``mtime_ns``, an ``__input__`` entry of both archives) is skipped; an input that
changed since, or whose earlier conversion met a bad tail, is converted again. The same file listed twice
(or under two spellings) is converted once. A corrupt input does not stop the run; it is reported under
``failed`` and nothing is written for it. A corrupt record inside an intact framing is skipped and listed.
"""

from __future__ import annotations

import io
import json
import os
import sys
import time
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from trajeglish_env.distributed import Ranks, gather, my_share
from trajeglish_env.metrics.log_details_io import details_path, load_log_details, save_log_details
from trajeglish_env.metrics.womd_details import parse_womd_details
from trajeglish_env.scenario_io import atomic_path, load_scenarios, save_scenarios
from trajeglish_env.sources.womd import good_records, no_records_error, output_name, parse_scenario
from trajeglish_env.sources.womd_tfrecord import TFRecordFramingError, WomdFormatError
from trajeglish_env.worker_pool import worker_pool

__all__ = ["check_inputs", "convert_file", "convert_womd", "unique_inputs"]

_INPUT_KEY = "__input__"  # entry of both outputs: the input's size and mtime_ns, and whether its tail was bad


def _input_identity(path: str) -> dict[str, int]:
    """What tells a changed input from the one converted before: its size and modification time (ns)."""
    stat = os.stat(path)
    return {"size": int(stat.st_size), "mtime_ns": int(stat.st_mtime_ns)}


def _stamp(archive: Path, record: dict[str, Any]) -> None:
    """Add the ``__input__`` entry (``record`` as JSON) to an ``.npz`` archive; readers ignore it."""
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, np.array(json.dumps(record, sort_keys=True)), allow_pickle=False)
    with zipfile.ZipFile(archive, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(_INPUT_KEY + ".npy", buffer.getvalue())


def _stamped(archive: Path) -> dict[str, Any] | None:
    """The ``__input__`` record of an archive written by this module (None if it has none)."""
    with np.load(archive, allow_pickle=False) as data:
        if _INPUT_KEY not in data.files:
            return None
        return json.loads(str(data[_INPUT_KEY]))


def _existing_scenes(target: Path, identity: dict[str, int]) -> tuple[int | None, str]:
    """Scenes of an already converted input (shard and details both load, agree and were made from this
    very input, which had no bad tail), else None, with why it must be converted (again)."""
    if not (target.is_file() and details_path(target).is_file()):
        return None, ""
    try:
        scenes, details = load_scenarios(target), load_log_details(details_path(target))
        stamps = [_stamped(target), _stamped(details_path(target))]
    except (ValueError, OSError, zipfile.BadZipFile):
        return None, "its outputs are unreadable"
    if len(scenes) != len(details):
        return None, "its outputs disagree"
    if None in stamps or stamps[0] != stamps[1]:
        return None, "its outputs do not record which input they were made from"
    stamp = stamps[0]
    assert stamp is not None
    if any(stamp.get(key) != value for key, value in identity.items()):
        return None, "it changed since it was converted (size or modification time)"
    if stamp.get("bad_tail"):
        return None, "it was converted with a truncated or corrupt tail"
    return len(scenes), ""


def _save(out: Path, scenes: list, details: list, stamp: dict[str, Any]) -> None:
    """Write the details, then the shard (each atomically, each stamped with the input's identity)."""
    for path, save, items in ((details_path(out), save_log_details, details), (out, save_scenarios, scenes)):
        with atomic_path(path) as tmp:
            save(tmp, items)
            _stamp(tmp, stamp)


def convert_file(path: str, target: str) -> dict[str, Any]:
    """Convert one TFRecord file; returns ``{"status": converted|skipped|failed, "scenes", "error",
    "bad_tail", "bad_records", "reconverted"}`` (``bad_tail``: what was kept of a file whose good records
    end in a truncated or corrupt tail, with the warning line; ``bad_records``: the corrupt records skipped
    in the middle, with their warning lines; ``reconverted``: why outputs already there were replaced)."""
    out = Path(target)
    try:
        identity = _input_identity(path)
    except OSError as exc:
        return {"status": "failed", "scenes": 0, "error": f"{path}: {exc.strerror or exc}"}
    existing, reason = _existing_scenes(out, identity)
    if existing is not None:
        return {"status": "skipped", "scenes": existing}
    bad: list[TFRecordFramingError] = []
    try:
        records, tail = good_records(path, bad)
        if not records:
            raise no_records_error(path)
        scenes, details = [], []
        for index, data in records:
            origin = f"{path}: record {index}"
            scenes.append(parse_scenario(data, origin=origin))
            details.append(parse_womd_details(data, origin=origin))
        _save(out, scenes, details, {**identity, "bad_tail": tail is not None, "bad_records": len(bad)})
    except (ValueError, OSError) as exc:  # WomdFormatError, ScenarioError, unreadable file
        return {"status": "failed", "scenes": 0, "error": str(exc)}
    result: dict[str, Any] = {"status": "converted", "scenes": len(scenes)}
    if reason:
        result["reconverted"] = reason
    if bad:
        result["bad_records"] = [
            {
                "entry": {"file": path, "record": b.record, "byte_offset": b.offset, "error": str(b)},
                "warning": f"{b.path}: skipped corrupt record {b.record} (byte offset {b.offset}): "
                f"{b.problem}; read on",
            }
            for b in bad
        ]
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


def unique_inputs(
    paths: Sequence[str | os.PathLike[str]],
) -> tuple[list[Path], list[dict[str, str]]]:
    """``paths`` without repeats of one file (the same path, another spelling of it or a link to it:
    compared by device and inode, else by resolved path), and ``{"file", "same_as"}`` for each repeat,
    both spelled as given (``./a`` stays ``./a``)."""
    seen: dict[object, str] = {}
    unique: list[Path] = []
    duplicates: list[dict[str, str]] = []
    for given in paths:
        path, spelling = Path(given), os.fspath(given)
        try:
            stat = path.stat()
            key: object = (stat.st_dev, stat.st_ino)
        except OSError:
            key = path.resolve()
        if key in seen:
            duplicates.append({"file": spelling, "same_as": seen[key]})
        else:
            seen[key] = spelling
            unique.append(path)
    return unique, duplicates


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
    with worker_pool(min(workers, len(jobs))) as pool:  # spawned; Ctrl-C / SIGTERM end the workers at once
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
    the tail is listed under ``bad_tails`` and reported on stderr. A record whose data checksum fails while
    the framing around it is intact is skipped, listed under ``bad_records`` (file, record, byte offset) and
    reported on stderr; the records after it are kept. Inputs naming one file twice are de-duplicated
    (``duplicates``: ``{"file", "same_as"}``, and a note on stderr). ``reconverted``: the inputs whose
    earlier outputs were replaced, with why. Returns (on every rank, merged over ranks) ``{"converted",
    "skipped", "failed", "bad_tails", "bad_records", "reconverted", "duplicates", "outputs", "scenes",
    "scenes_skipped", "processes", "workers", "seconds"}``; lists are in input order.
    """
    start = time.perf_counter()
    ranks = ranks or Ranks()
    out = Path(out)
    paths, duplicates = unique_inputs(files)
    if ranks.main:
        for entry in duplicates:
            file, same = entry["file"], entry["same_as"]
            what = "given again" if file == same else f"the same file as {same}"
            note = f"{file} is {what}: converted once"
            tqdm.write(f"convert-womd: note: {note}", file=sys.stderr)
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
        for bad in result.get("bad_records", []):
            bar.write(f"convert-womd: warning: {bad['warning']}", file=sys.stderr)
        if "bad_tail" in result:
            bar.write(f"convert-womd: warning: {result['bad_tail']['warning']}", file=sys.stderr)
        if "reconverted" in result:
            bar.write(
                f"convert-womd: note: {paths[i]}: converted again: {result['reconverted']}", file=sys.stderr
            )
        bar.update(1)
        bar.set_postfix(scenes=sum(r["scenes"] for _, r in done))
    bar.close()
    merged = sorted((item for part in gather(done, ranks) for item in part), key=lambda item: item[0])
    report: dict[str, Any] = {
        "converted": [],
        "skipped": [],
        "failed": [],
        "bad_tails": [],
        "bad_records": [],
    }
    report.update(reconverted=[], duplicates=duplicates, outputs=[])
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
            report["bad_records"].extend(bad["entry"] for bad in result.get("bad_records", []))
            if "reconverted" in result:
                report["reconverted"].append({"file": name, "reason": result["reconverted"]})
            report["converted"].append(name)
            report["outputs"].append(str(out / output_name(paths[i])))
            report["scenes"] += result["scenes"]
    report.update(processes=ranks.world, workers=workers, seconds=time.perf_counter() - start)
    return report
