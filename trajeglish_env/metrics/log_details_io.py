"""Files of raw WOMD log values (:class:`LogDetails`) kept beside converted scenario shards.

``convert-womd`` writes ``NAME.details.npz`` next to ``NAME.scn.npz``, one entry per scene in the same
order, so that what the planar :class:`~trajeglish_env.scenario.Scenario` drops (z, box heights, raw
invalid states, object types, map z, per-step stop points) is there for the submission's ``center_z`` and
for scores that match the official ones, without the TFRecords. Written atomically; a foreign or
mismatched file fails with a message naming it.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

import numpy as np

from trajeglish_env.metrics.log_details import LogDetails
from trajeglish_env.scenario_io import SUFFIX, atomic_path, load_failure, scenario_ids

__all__ = ["DETAILS_SUFFIX", "details_for_files", "details_path", "load_log_details", "save_log_details"]

DETAILS_SUFFIX = ".details.npz"
FORMAT_NAME = "trajeglish_env.log_details"
FORMAT_VERSION = 1


def details_path(scenario_file: str | os.PathLike[str]) -> Path:
    """The details file that belongs to a scenario shard (``x.scn.npz`` -> ``x.details.npz``)."""
    path = Path(scenario_file)
    stem = path.name[: -len(SUFFIX)] if path.name.endswith(SUFFIX) else path.stem
    return path.with_name(stem + DETAILS_SUFFIX)


def save_log_details(path: str | os.PathLike[str], details: Sequence[LogDetails]) -> Path:
    """Write the details of a shard's scenes (in the shard's order) atomically."""
    arrays: dict[str, np.ndarray] = {
        "__format__": np.array(FORMAT_NAME),
        "__version__": np.array(FORMAT_VERSION),
        "__count__": np.array(len(details)),
    }
    for i, item in enumerate(details):
        for f in fields(LogDetails):
            arrays[f"{i}/{f.name}"] = np.asarray(getattr(item, f.name))
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
    return path


def load_log_details(path: str | os.PathLike[str]) -> list[LogDetails]:
    """Read a details file written by :func:`save_log_details`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such log-details file")
    try:
        with np.load(path, allow_pickle=False) as data:
            named = "__format__" in data.files and str(data["__format__"]) == FORMAT_NAME
            version = int(data["__version__"]) if named else None
            if named and version == FORMAT_VERSION:
                count = int(data["__count__"])
                names = [f.name for f in fields(LogDetails)]
                return [LogDetails(**{n: data[f"{i}/{n}"] for n in names}) for i in range(count)]
    except (zipfile.BadZipFile, EOFError, OSError, KeyError, ValueError) as exc:
        raise ValueError(
            f"{path}: not a readable log-details file (truncated or corrupt?): {load_failure(exc)}"
        ) from exc
    if not named:
        raise ValueError(f"{path}: not a log-details file (no '{FORMAT_NAME}' header)")
    raise ValueError(f"{path}: log-details version {version} is not supported")


def details_for_files(files: Sequence[str | os.PathLike[str]]) -> list[LogDetails | None]:
    """Details of every scene of the given shards in order: None for the scenes of a shard without its
    details file (each shard on its own: one shard without them leaves the others' details in use)."""
    out: list[LogDetails | None] = []
    for f in files:
        sidecar, count = details_path(f), len(scenario_ids(f))
        if not sidecar.is_file():
            out += [None] * count
            continue
        details = load_log_details(sidecar)
        if len(details) != count:
            raise ValueError(
                f"{sidecar}: holds details of {len(details)} scenes, {f} holds {count}: not its shard's "
                "(convert the TFRecord again with `trajeglish convert-womd`)"
            )
        out += details
    return out
