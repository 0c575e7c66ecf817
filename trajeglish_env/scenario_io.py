"""Versioned, compressed on-disk format for Scenarios, with atomic writes.

A file (``*.scn.npz``) holds one or more scenes (a "shard"). It is a NumPy ``.npz`` archive whose
``__format__`` entry names this format and whose ``__version__`` entry is checked on load, so a wrong,
truncated or future file fails with a message naming the file instead of a NumPy traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from trajeglish_env.scenario import Scenario, ScenarioError

FORMAT_NAME = "trajeglish_env.scenario"
FORMAT_VERSION = 1
SUFFIX = ".scn.npz"

_SCALARS = {"sdc": int, "scenario_id": str, "source": str, "dt": float, "current_index": int}


def load_failure(exc: BaseException, expected: str = "a NumPy .npz archive written by trajeglish") -> str:
    """One line saying why NumPy or torch could not read a file, in place of their advice to load pickled
    data unsafely (a file of trajeglish's never holds pickled objects): an error message's reason."""
    text = str(exc)
    if "allow_pickle" in text or "pickled (object) data" in text:  # NumPy met pickled objects or no archive
        return f"not {expected} (it holds pickled objects or is not an archive)"
    marker = "WeightsUnpickler error:"
    if marker in text:  # torch's weights-only unpickler met something that is not a checkpoint's data
        text = text.split(marker, 1)[1]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return f"{type(exc).__name__}: {(lines[0] if lines else 'no details')[:200]}"


def scenario_fields() -> list[str]:
    """Names of all Scenario fields, in declaration order."""
    return [f.name for f in dataclasses.fields(Scenario)]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one rename.

    A crash or exception leaves any previous ``path`` untouched and no partial file behind.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # keep the real suffix last so that writers choosing a format by extension (video) still work
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600; give the file normal permissions
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def save_scenarios(path: str | os.PathLike[str], scenarios: Sequence[Scenario]) -> Path:
    """Validate and write ``scenarios`` to ``path`` atomically; returns the path."""
    if not isinstance(path, (str, os.PathLike)) or isinstance(scenarios, (str, os.PathLike, Scenario)):
        raise TypeError(
            f"save_scenarios(path, scenarios): expected a file path and a list of Scenario objects, got "
            f"{type(path).__name__} and {type(scenarios).__name__}"
            + (" (swapped?)" if isinstance(scenarios, (str, os.PathLike)) else "")
        )
    bad = [i for i, sc in enumerate(scenarios) if not isinstance(sc, Scenario)]
    if bad:
        raise TypeError(
            f"save_scenarios: scenarios[{bad[0]}] is a {type(scenarios[bad[0]]).__name__}, not a Scenario"
        )
    arrays: dict[str, np.ndarray] = {
        "__format__": np.array(FORMAT_NAME),
        "__version__": np.array(FORMAT_VERSION),
        "__count__": np.array(len(scenarios)),
    }
    for i, sc in enumerate(scenarios):
        sc.validate()
        for name in scenario_fields():
            value = getattr(sc, name)
            if value is None:
                continue
            arrays[f"{i}/{name}"] = np.asarray(value)
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
    return path


def load_scenarios(path: str | os.PathLike[str]) -> list[Scenario]:
    """Read every scene of a file written by :func:`save_scenarios`; clear errors for bad files."""
    path = Path(path)
    header, items = _read_shard(path, header_only=False)
    scenes = []
    for i in range(header):
        kwargs: dict[str, object] = {}
        for name in scenario_fields():
            key = f"{i}/{name}"
            if key not in items:
                if name == "signal_state":
                    continue
                raise ScenarioError(f"{path}: scene {i} is missing field '{name}'")
            value = items[key]
            kwargs[name] = _SCALARS[name](value.item()) if name in _SCALARS else value
        try:
            scenes.append(Scenario(**kwargs).validate())  # type: ignore[arg-type]
        except ScenarioError as exc:
            raise ScenarioError(f"{path}: scene {i}: {exc}") from exc
    return scenes


def count_scenarios(path: str | os.PathLike[str]) -> int:
    """Number of scenes in a scenario file, from its header only (cheap); clear errors for bad files."""
    return _read_shard(Path(path), header_only=True)[0]


# What NumPy and zipfile raise for truncated, corrupt or foreign files (zlib.error: a damaged deflate stream).
_UNREADABLE = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError)


def _read_shard(path: Path, header_only: bool) -> tuple[int, dict[str, np.ndarray]]:
    """The scene count and (unless ``header_only``) every array of a scenario file.

    Any failure of NumPy or zipfile becomes a :class:`ScenarioError` naming the file.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {_missing_file(path)}")
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ScenarioError(
                f"{path}: not a trajeglish_env scenario file (a bare NumPy array, not an archive)"
            )
        with data:
            count = _check_header(path, data)
            items = {} if header_only else {k: data[k] for k in data.files}
    except ScenarioError:
        raise
    except _UNREADABLE as exc:
        raise _unreadable(path, exc) from exc
    return count, items


def _scene_strings(path: str | os.PathLike[str], name: str) -> list[str]:
    """One string field of every scene of a file, read without loading the scenes."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {_missing_file(path)}")
    try:
        with np.load(path, allow_pickle=False) as data:
            return [str(data[f"{i}/{name}"]) for i in range(_check_header(path, data))]
    except ScenarioError:
        raise
    except _UNREADABLE as exc:
        raise _unreadable(path, exc) from exc


def scenario_ids(path: str | os.PathLike[str]) -> list[str]:
    """The scenario ids of a file's scenes, read without loading the scenes (indexing large sets)."""
    return _scene_strings(path, "scenario_id")


def scene_sources(path: str | os.PathLike[str]) -> list[str]:
    """The sources of a file's scenes (one per scene), read without loading the scenes."""
    return _scene_strings(path, "source")


def _check_header(path: Path, data: np.lib.npyio.NpzFile) -> int:
    """The scene count of an archive whose header names this format and version."""
    if "__format__" not in data.files or str(data["__format__"]) != FORMAT_NAME:
        raise ScenarioError(f"{path}: not a trajeglish_env scenario file (no '{FORMAT_NAME}' header)")
    version = int(data["__version__"])
    if version != FORMAT_VERSION:
        raise ScenarioError(
            f"{path}: scenario format version {version} is not supported (this build reads {FORMAT_VERSION})"
        )
    count = int(data["__count__"])
    if count < 0:
        raise ScenarioError(f"{path}: header field '__count__': expected a scene count >= 0, got {count}")
    return count


def save_scenario(path: str | os.PathLike[str], scenario: Scenario) -> Path:
    """Write a single scene (a shard of one)."""
    return save_scenarios(path, [scenario])


def load_scenario(path: str | os.PathLike[str], index: int = 0) -> Scenario:
    """Read scene ``index`` of a scenario file."""
    scenes = load_scenarios(path)
    if not 0 <= index < len(scenes):
        raise IndexError(f"{path}: scene {index} requested but the file holds {len(scenes)}")
    return scenes[index]


def list_scenario_files(directory: str | os.PathLike[str]) -> list[Path]:
    """Sorted scenario files under ``directory`` (or ``[directory]`` if it is itself a file)."""
    directory = Path(directory)
    if directory.is_file():
        return [directory]
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such scenario file or directory")
    return sorted(p for p in directory.rglob(f"*{SUFFIX}") if not p.name.startswith("."))


def scenario_files(paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]) -> list[Path]:
    """Every scenario file under the given files/directories (sorted per path); a FileNotFoundError when
    there is none, which says to convert first when WOMD TFRecords are there instead."""
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    files = [f for p in paths for f in list_scenario_files(p)]
    if not files:
        raise FileNotFoundError(no_scenario_files_message(paths))
    return files


def no_scenario_files_message(paths: Sequence[str | os.PathLike[str]]) -> str:
    """ "No scenario files under ...", with the convert-womd hint when TFRecord files are there."""
    records = [f for p in map(Path, paths) if p.is_dir() for f in p.rglob("*tfrecord*") if f.is_file()]
    hint = (
        f" (there are WOMD TFRecord files, e.g. {records[0]}: convert them first, `trajeglish convert-womd "
        "FILES --out DIR`, and pass DIR)"
        if records
        else ""
    )
    return f"no scenario files (*.scn.npz) under {[str(p) for p in paths]}{hint}"


def _looks_like_tfrecord(path: Path) -> bool:
    """A WOMD TFRecord given where a scenario file is expected (by its name; scenario files are zips)."""
    return "tfrecord" in path.name.lower()


def _unreadable(path: Path, exc: BaseException) -> ScenarioError:
    """The error for a file NumPy cannot read as a scenario archive."""
    if _looks_like_tfrecord(path):
        return ScenarioError(
            f"{path}: a WOMD TFRecord file, not a scenario file (*.scn.npz): convert it first, `trajeglish "
            "convert-womd FILE --out DIR`, and pass DIR"
        )
    return ScenarioError(f"{path}: not a readable scenario file (truncated or corrupt?): {load_failure(exc)}")


def _missing_file(path: Path) -> str:
    """Why a scenario file path is not one (an error message's)."""
    return "a directory, not a scenario file (*.scn.npz)" if path.is_dir() else "no such scenario file"
