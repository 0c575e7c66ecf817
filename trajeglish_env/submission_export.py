"""``trajeglish export-submission``: closed-loop rollouts of every scenario of a set of converted shards,
written as official Waymo Sim Agents submission shards and packed for upload.

For each scenario the model drives the *sim agents* as WOSAC defines them (every agent valid at the
current step, 10 for WOMD) for ``steps`` (80) steps, ``rollouts`` (32) times, from the history alone (the
log's future, late-appearing agents and future signal states included, is cut off before sampling, so a
validation scene is simulated exactly as a test scene). ``center_z`` is each agent's logged z at the
current step, from the raw log details ``convert-womd`` keeps beside the shard (0 for generated scenes).

Layout of ``OUT``: ``export.json`` (the settings; a resumed run must match them), ``parts/`` (one file
per finished scenario, written atomically), ``PREFIX.binproto-KKKKK-of-NNNNN`` (submission shard k holds
the scenarios of input shard k, in order, behind the metadata) and ``PREFIX.tar.gz`` (the shards, packed
reproducibly). Each scenario's seed is derived from its id (:func:`scenario_seed`), so the files do not
depend on the number of ``torchrun`` ranks sharing the scenarios, nor on interruptions.
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import itertools
import json
import reprlib
import shutil
import sys
import tarfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.distributed import Ranks, barrier, gather, my_share
from trajeglish_env.metrics.log_details import LogDetails
from trajeglish_env.metrics.log_details_io import details_path, load_log_details
from trajeglish_env.metrics.submission import SubmissionMetadata, SubmittedRollouts, encode_scenario
from trajeglish_env.sampler import rollout
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.scenario import Scenario, scenario_seed
from trajeglish_env.scenario_io import (
    atomic_path,
    load_scenarios,
    scenario_files,
    scenario_ids,
)

__all__ = [
    "ExportConfig",
    "export_submission",
    "history_only",
    "sample_scenario",
    "scenario_seed",
    "sim_agents",
]

MANIFEST = "export.json"


WOSAC_STEPS = 80  # a submission's simulated steps after the current one (8 s at 10 Hz), what scoring needs


@dataclass(frozen=True)
class ExportConfig:
    """What to sample (WOSAC: 32 rollouts x 80 steps) and how, and the output files' ``prefix``."""

    rollouts: int = 32
    steps: int = WOSAC_STEPS
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    seed: int = 0
    prefix: str = "submission"
    # processes each scenario's rollouts are split over (``rollout(..., processes=...)``: the same rollouts)
    processes: int | str = 1

    def __post_init__(self) -> None:
        if self.rollouts < 1 or self.steps < 1:
            raise ValueError(
                f"ExportConfig: rollouts and steps must be >= 1, got {self.rollouts}, {self.steps}"
            )
        if self.processes != "auto" and (
            isinstance(self.processes, bool) or not isinstance(self.processes, int) or self.processes < 1
        ):
            raise ValueError(
                f"ExportConfig: processes must be a positive int or 'auto', got {self.processes!r}"
            )


def sim_agents(scene: Scenario) -> np.ndarray:
    """Indices of the agents WOSAC simulates: those valid at the current step."""
    return np.flatnonzero(scene.valid[:, scene.current_index])


def history_only(scene: Scenario) -> Scenario:
    """The scene up to its current step (what a test-set scene holds): no future states or signals, and
    no agent that only the future holds (rows without a state would shift the agents' random draws, so a
    validation scene would not be simulated exactly as its test-form twin)."""
    keep = scene.current_index + 1
    signals = None if scene.signal_state is None else scene.signal_state[:keep].copy()
    cut = replace(
        scene, xyh=scene.xyh[:, :keep].copy(), valid=scene.valid[:, :keep].copy(), signal_state=signals
    )
    seen = cut.valid.any(axis=1)
    seen[scene.sdc] = True
    return cut if seen.all() else cut.with_agents(np.flatnonzero(seen))


def sample_scenario(
    ckpt: Checkpoint, scene: Scenario, details: LogDetails | None, config: ExportConfig
) -> SubmittedRollouts:
    """Closed-loop rollouts of one scenario's sim agents, as submitted (float32, z held at the log's)."""
    sim = sim_agents(scene)
    if len(sim) == 0:
        raise ValueError(f"scenario {scene.scenario_id!r}: no agent is valid at the current step")
    sampling = replace(config.sampling, seed=scenario_seed(config.seed, scene.scenario_id))
    past = history_only(scene)
    result = rollout(ckpt, past, config.rollouts, config.steps, config=sampling, processes=config.processes)
    future = result.xyh[:, sim_agents(past), scene.current_index + 1 :]  # the same agents, in the same order
    z = np.zeros(len(sim)) if details is None else details.xyz[sim, scene.current_index, 2]
    xyz = np.concatenate(
        [future[..., :2], np.broadcast_to(z[None, :, None, None], (*future.shape[:3], 1))], -1
    )
    return SubmittedRollouts(
        scenario_id=scene.scenario_id,
        object_id=scene.track_id[sim].astype(np.int64),
        xyz=xyz.astype(np.float32),
        heading=future[..., 2].astype(np.float32),
    )


def _input_files(data: str | Path | Sequence[str | Path]) -> list[Path]:
    paths = [data] if isinstance(data, (str, Path)) else list(data)
    files = scenario_files(paths)
    return files


def _weights_digest(ckpt: Checkpoint) -> str:
    """A fingerprint of the model's weights (a resumed export must sample with the same model)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(ckpt.model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().float().cpu().numpy().tobytes())
    return digest.hexdigest()


def _manifest(files: list[Path], ckpt: Checkpoint, config: ExportConfig, meta: SubmissionMetadata) -> dict:
    settings = dataclasses.asdict(config)
    settings.pop("processes")  # how the rollouts are split never changes them: a resume may differ in it
    return {
        "format": "trajeglish_env.submission_export",
        "version": 1,
        "config": settings,
        "model": _weights_digest(ckpt),
        "metadata": meta.to_dict(),
        "inputs": [f.name for f in files],
    }


def _differences(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    """``name: old -> new`` for each field where two manifests differ (nested ones as ``config.seed``)."""
    out: list[str] = []
    for key in sorted(set(old) | set(new)):
        was, now, name = old.get(key, "(unset)"), new.get(key, "(unset)"), f"{prefix}{key}"
        if was == now:
            continue
        if isinstance(was, dict) and isinstance(now, dict):
            out += _differences(was, now, f"{name}.")
        elif key == "model" and not prefix:
            out.append("model: other weights")  # two digests say nothing more
        else:
            out.append(f"{name}: {reprlib.repr(was)} -> {reprlib.repr(now)}")
    return out


def _check_manifest(out: Path, manifest: dict, write: bool) -> None:
    """Refuse to mix settings in one output directory; the main rank writes the manifest of a new run."""
    path = out / MANIFEST
    if path.is_file():
        old = json.loads(path.read_text())
        differ = _differences(old, manifest)
        if differ:
            raise ValueError(
                f"{path}: this directory holds an export with other settings ({'; '.join(differ)}); "
                "use another --out or delete it"
            )
    elif write:
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(manifest, indent=2))


def _part(out: Path, shard: str, index: int) -> Path:
    return out / "parts" / shard / f"{index:06d}.binproto"


def _details_of(file: Path, scenes: list[Scenario]) -> list[LogDetails | None]:
    """Raw log details of a shard's scenes (None for generated scenes; WOMD shards need them)."""
    sidecar = details_path(file)
    if sidecar.is_file():
        details = load_log_details(sidecar)
        if len(details) != len(scenes):
            raise ValueError(f"{sidecar}: {len(details)} entries for the {len(scenes)} scenes of {file}")
        for item, scene in zip(details, scenes, strict=True):
            item.check_matches(scene)
        return list(details)
    if any(s.source == "womd" for s in scenes):
        raise FileNotFoundError(
            f"{sidecar}: missing (WOMD z values); convert the TFRecords again with convert-womd"
        )
    return [None] * len(scenes)


def _sample_parts(
    work: list[tuple[int, int]],
    files: list[Path],
    shards: list[str],
    ckpt: Checkpoint,
    config: ExportConfig,
    out: Path,
    progress: bool,
) -> int:
    """Sample and write this rank's scenarios (``(shard, index)`` pairs, grouped by shard)."""
    bar = tqdm(
        total=len(work), desc="export-submission", unit="scenario", file=sys.stderr, disable=not progress
    )
    for k, group in itertools.groupby(work, key=lambda item: item[0]):
        scenes = load_scenarios(files[k])
        details = _details_of(files[k], scenes)
        for _, j in group:
            item = sample_scenario(ckpt, scenes[j], details[j], config)
            with atomic_path(_part(out, shards[k], j)) as tmp:
                tmp.write_bytes(encode_scenario(item))
            bar.update(1)
    bar.close()
    return len(work)


def _assemble(out: Path, shard: str, count: int, head: bytes) -> None:
    """Write one submission shard (metadata, then its scenarios in order) and drop its parts."""
    parts = [_part(out, shard, j) for j in range(count)]
    missing = [p.name for p in parts if not p.is_file()]
    if missing:
        raise RuntimeError(f"{out / 'parts' / shard}: scenarios {missing[:3]} were not written")
    with atomic_path(out / shard) as tmp, open(tmp, "wb") as fh:
        fh.write(head)
        for part in parts:
            fh.write(part.read_bytes())
    shutil.rmtree(out / "parts" / shard, ignore_errors=True)


def pack_archive(shards: list[Path], archive: Path) -> Path:
    """A ``.tar.gz`` of the shards (flat names), byte-identical for identical shards."""
    with atomic_path(archive) as tmp, open(tmp, "wb") as raw:
        with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=6) as gz:
            with tarfile.open(fileobj=gz, mode="w", format=tarfile.GNU_FORMAT) as tar:
                for shard in shards:
                    info = tarfile.TarInfo(shard.name)
                    info.size, info.mtime, info.mode = shard.stat().st_size, 0, 0o644
                    with open(shard, "rb") as fh:
                        tar.addfile(info, fh)
    return archive


def export_submission(
    data: str | Path | Sequence[str | Path],
    ckpt: Checkpoint,
    out: str | Path,
    metadata: SubmissionMetadata,
    config: ExportConfig = ExportConfig(),
    progress: bool = True,
    ranks: Ranks | None = None,
) -> dict[str, Any]:
    """Sample, write and pack a submission for every scenario under ``data`` (see the module docstring);
    resumes an interrupted run at its first unfinished scenario. Returns a summary (on every rank)."""
    start, ranks, out = time.perf_counter(), ranks or Ranks(), Path(out)
    metadata.validate()
    files = _input_files(data)
    shards = [f"{config.prefix}.binproto-{k:05d}-of-{len(files):05d}" for k in range(len(files))]
    manifest = _manifest(files, ckpt, config, metadata)
    if ranks.main:
        _check_manifest(out, manifest, write=True)
    barrier(ranks)
    _check_manifest(out, manifest, write=False)
    ids = [scenario_ids(f) for f in files]
    every = [sid for group in ids for sid in group]
    if len(set(every)) != len(every):
        twice = sorted({s for s in every if every.count(s) > 1})
        raise ValueError(f"scenario ids {twice[:3]} appear more than once in the input shards")
    pending = [
        (k, j)
        for k, shard in enumerate(shards)
        if not (out / shard).is_file()
        for j in range(len(ids[k]))
        if not _part(out, shard, j).is_file()
    ]
    unassembled = [k for k in range(len(shards)) if not (out / shards[k]).is_file()]
    barrier(ranks)  # every rank has listed the pending scenarios and shards before any is written
    sampled = _sample_parts(my_share(pending, ranks), files, shards, ckpt, config, out, progress)
    barrier(ranks)
    head = metadata.encode()
    # the list of every rank, taken before anything was written: one rank's finished shard must not
    # shift the shares of the others (a shard nobody assembles)
    for k in my_share(unassembled, ranks):
        _assemble(out, shards[k], len(ids[k]), head)
    barrier(ranks)
    archive = out / f"{config.prefix}.tar.gz"
    if ranks.main:
        pack_archive([out / s for s in shards], archive)
        if (out / "parts").is_dir() and not any((out / "parts").iterdir()):
            (out / "parts").rmdir()
    barrier(ranks)
    return {
        "archive": str(archive),
        "archive_bytes": archive.stat().st_size,
        "shards": [str(out / s) for s in shards],
        "scenarios": len(every),
        "sampled": sum(gather(sampled, ranks)),
        "resumed": len(every) - len(pending),
        "rollouts": config.rollouts,
        "steps": config.steps,
        "processes": ranks.world,
        "seconds": round(time.perf_counter() - start, 2),
    }
