"""Parallel, resumable, atomic generation of scene shards from any built-in scene source.

A run of N scenes is split into fixed shards of ``scenes_per_shard`` scenes. Shard ``i`` is a pure
function of (source, kinds, seed, i), so the output does not depend on the number of workers and an
interrupted run resumes by generating only the shards whose files are missing. Each shard file is
written atomically (temporary file + rename), so a crash never leaves a half-written shard, and a
``manifest.json`` records the run's settings so that resuming with different settings is refused.
"""

from __future__ import annotations

import importlib
import json
import os
import sys
import time
import warnings
import zipfile
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

from tqdm import tqdm

from trajeglish_env.distributed import Ranks, barrier, gather, my_share
from trajeglish_env.scenario import Scenario
from trajeglish_env.scenario_io import SUFFIX, atomic_path, save_scenarios, scenario_ids
from trajeglish_env.worker_pool import worker_pool

MANIFEST = "manifest.json"

# Source name -> module implementing ``generate_shard`` (imported lazily in each worker).
SOURCES = {"highway": "trajeglish_env.sources.highway", "sumo": "trajeglish_env.sources.sumo"}


class SceneSource(Protocol):
    """What a scene-source module provides: its scene kinds (default ones; an optional ``EXTRA_KINDS``
    tuple lists kinds taken only when asked for) and a pure shard generator."""

    KINDS: tuple[str, ...]

    def generate_shard(
        self, kinds: tuple[str, ...], seed: int, shard_index: int, count: int, capacity: int | None = None
    ) -> list[Scenario]:
        """Return ``count`` scenes, a deterministic function of the arguments; ``capacity``, a full shard's
        scene count: a partial shard holds the first scenes of the full one."""
        ...


@dataclass(frozen=True)
class GenerationConfig:
    """Settings of one generation run (recorded in the manifest; a resume must match them)."""

    source: str
    scenes: int
    seed: int = 0
    kinds: tuple[str, ...] = ()
    scenes_per_shard: int = 8

    @property
    def num_shards(self) -> int:
        return -(-self.scenes // self.scenes_per_shard)

    def shard_count(self, index: int) -> int:
        return min(self.scenes_per_shard, self.scenes - index * self.scenes_per_shard)


def load_source(name: str) -> SceneSource:
    """Import the scene source called ``name`` (``highway`` or ``sumo``)."""
    if name not in SOURCES:
        raise ValueError(f"unknown scene source {name!r}; expected one of {sorted(SOURCES)}")
    return importlib.import_module(SOURCES[name])  # type: ignore[return-value]


def shard_path(out: Path, config: GenerationConfig, index: int) -> Path:
    return out / f"{config.source}-{index:05d}{SUFFIX}"


def _write_shard(config: GenerationConfig, index: int, out: str) -> tuple[int, int, float]:
    """Worker: generate shard ``index`` and write it atomically; returns (index, scenes, seconds)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    start = time.perf_counter()
    source = load_source(config.source)
    count = config.shard_count(index)
    scenes = source.generate_shard(config.kinds, config.seed, index, count, capacity=config.scenes_per_shard)
    save_scenarios(shard_path(Path(out), config, index), scenes)
    return index, len(scenes), time.perf_counter() - start


def _shard_complete(path: Path, expected: int) -> bool:
    """A shard is done when its file holds the expected scenes and every member passes its CRC check (a
    damaged shard is made again; the check decompresses the shard, about 20 ms a megabyte-sized shard, but
    parses no scene)."""
    if not path.is_file():
        return False
    try:
        with zipfile.ZipFile(path) as archive:
            if archive.testzip() is not None:
                return False
        return len(scenario_ids(path)) == expected
    except (ValueError, OSError, zipfile.BadZipFile, EOFError):
        return False


MANIFEST_FORMAT, MANIFEST_VERSION = "trajeglish_env.shards", 1


def _read_manifest(manifest: Path) -> dict:
    """A generate folder's manifest; a ValueError naming it when it is not one of ours."""
    try:
        have = json.loads(manifest.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{manifest}: not a readable manifest (corrupt?): {exc}") from exc
    if not isinstance(have, dict) or have.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{manifest}: not a scene folder's manifest (expected format {MANIFEST_FORMAT!r})")
    if have.get("version") != MANIFEST_VERSION:
        raise ValueError(
            f"{manifest}: manifest version {have.get('version')!r}, this build reads {MANIFEST_VERSION}: "
            "written by another version; use another --out directory"
        )
    return have


def _check_manifest(out: Path, config: GenerationConfig) -> None:
    """Record the run's settings and its source's ``GENERATOR_VERSION`` (scenes of another version
    differ, e.g. highway-env's kerb corners), or refuse to resume a directory made with others."""
    manifest = out / MANIFEST
    want = asdict(config)
    want["kinds"] = list(config.kinds)
    generator = int(getattr(load_source(config.source), "GENERATOR_VERSION", 1))
    ours = {shard_path(out, config, k).name for k in range(config.num_shards)}
    foreign = sorted(f.name for f in out.glob(f"*{SUFFIX}") if f.name not in ours)
    if foreign:
        raise ValueError(
            f"{out}: holds scene files this run would not write ({', '.join(foreign[:3])}"
            f"{', ...' if len(foreign) > 3 else ''}): another source's, another --scenes-per-shard's or "
            "another tool's; refusing to mix them. Use another --out directory."
        )
    if not manifest.is_file() and any(out.glob(f"*{SUFFIX}")):
        raise ValueError(
            f"{out}: holds scene shards but no {MANIFEST} (made by an older version or another tool, or its "
            "manifest was deleted): their settings are unknown, so they are not resumed. Use another --out "
            "directory."
        )
    if manifest.is_file():
        have = _read_manifest(manifest)
        if have.get("config") != want:
            raise ValueError(
                f"{manifest}: this directory was generated with different settings {have.get('config')}; "
                f"refusing to mix them with {want}. Use another --out directory."
            )
        if int(have.get("generator_version", 1)) != generator:
            raise ValueError(
                f"{manifest}: this directory was generated by version {have.get('generator_version', 1)} "
                f"of the {config.source} generator, this is version {generator}; refusing to mix their "
                "scenes. Use another --out directory."
            )
        return
    with atomic_path(manifest) as tmp:
        doc = {
            "format": MANIFEST_FORMAT,
            "version": MANIFEST_VERSION,
            "generator_version": generator,
            "config": want,
        }
        tmp.write_text(json.dumps(doc, indent=2))


def generate(
    config: GenerationConfig,
    out: str | os.PathLike[str],
    workers: int = 1,
    progress: bool = True,
    ranks: Ranks | None = None,
) -> dict:
    """Generate (or finish generating) ``config.scenes`` scenes into ``out``; returns a summary dict.

    Under ``torchrun`` the missing shards are shared over the ranks (every ``world``-th one), each rank
    using ``workers`` processes; shards depend only on their index, so the files are the one-process ones.
    """
    ranks = ranks or Ranks()
    source = load_source(config.source)
    kinds = config.kinds or source.KINDS
    known = tuple(source.KINDS) + tuple(getattr(source, "EXTRA_KINDS", ()))
    unknown = sorted(set(kinds) - set(known))
    if unknown:
        raise ValueError(f"--kinds: unknown {config.source} scene kinds {unknown}; expected some of {known}")
    if config.scenes < 1 or config.scenes_per_shard < 1:
        raise ValueError("--scenes and scenes_per_shard must be >= 1")
    config = GenerationConfig(
        config.source, config.scenes, config.seed, tuple(kinds), config.scenes_per_shard
    )
    check = getattr(source, "check_available", None)
    if check is not None:  # e.g. SUMO not installed: said before any folder is made
        check()
    kind_scenes = _kind_scenes(source, config)
    idle = [k for k, n in (kind_scenes or {}).items() if n == 0]
    if idle and ranks.main:
        warnings.warn(
            f"--kinds: {', '.join(idle)} get no scene: each {config.source} shard of "
            f"{config.scenes_per_shard} scenes is one network of one kind, drawn per shard, and "
            f"{config.scenes} scenes make {config.num_shards} shard(s) ({kind_scenes}); ask for more scenes "
            "or pass a smaller --scenes-per-shard",
            UserWarning,
            stacklevel=2,
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if ranks.main:
        _check_manifest(out, config)
    barrier(ranks)
    _check_manifest(out, config)
    missing = [
        i
        for i in range(config.num_shards)
        if not _shard_complete(shard_path(out, config, i), config.shard_count(i))
    ]
    done_before = config.scenes - sum(config.shard_count(i) for i in missing)
    barrier(ranks)  # every rank has listed the missing shards before any is written
    todo = my_share(missing, ranks)
    start = time.perf_counter()
    bar = tqdm(
        total=config.scenes,
        initial=done_before,
        unit="scene",
        disable=not progress,
        file=sys.stderr,
        desc=f"generate {config.source}",
    )
    generated = 0
    if workers <= 1 or len(todo) <= 1:
        for i in todo:
            generated += _write_shard(config, i, str(out))[1]
            bar.update(config.shard_count(i))
    else:
        with worker_pool(workers) as pool:  # Ctrl-C / SIGTERM: queued shards cancelled, workers ended
            pending = {pool.submit(_write_shard, config, i, str(out)) for i in todo}
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    _, count, _ = fut.result()
                    generated += count
                    bar.update(count)
    bar.close()
    generated = sum(gather(generated, ranks))
    elapsed = time.perf_counter() - start
    return {
        "out": str(out),
        "source": config.source,
        "kinds": list(config.kinds),
        "seed": config.seed,
        "scenes": config.scenes,
        "shards": config.num_shards,
        "kind_scenes": kind_scenes,  # scenes per kind where a shard is one kind (SUMO), else None
        "generated": generated,
        "resumed_from": done_before,
        "seconds": round(elapsed, 3),
        "scenes_per_second": round(generated / elapsed, 3) if generated and elapsed > 0 else None,
        "workers": workers,
        "processes": ranks.world,
    }


def _kind_scenes(source: Any, config: GenerationConfig) -> dict[str, int] | None:
    """Scenes of each kind where a source draws one kind per shard (its ``shard_kind``), else None."""
    shard_kind = getattr(source, "shard_kind", None)
    if shard_kind is None:
        return None
    counts = dict.fromkeys(config.kinds, 0)
    for i in range(config.num_shards):
        counts[shard_kind(config.kinds, config.seed, i)] += config.shard_count(i)
    return counts


def scene_seed(seed: int, shard_index: int, slot: int) -> int:
    """A well-mixed 32-bit seed for one scene, independent of the worker that builds it."""
    import numpy as np

    return int(np.random.SeedSequence([seed, shard_index, slot]).generate_state(1)[0])
