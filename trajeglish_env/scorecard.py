"""``trajeglish scorecard``: every target row of the NPC-quality issue for one or more checkpoints, in one
command: guarded realism per scene source, the model alone against constant velocity, partial control, the
brake test, 30 s rollouts, the shared WOMD scene, the demo episode and tokenization within 5 cm.

The held-out scenes are generated with fixed seeds (``trajeglish generate``; resumed when present), so two
runs on two machines score the same scenes. Each part of each checkpoint is saved as it finishes, keyed by
the checkpoint file's sha256, the part's settings and a digest of the package's code: a run that stops
resumes where it stopped, a candidate is scored beside an earlier run's rows of the shipped model without
recomputing them, and a part computed by other code (a changed guard, say) is computed again. With
``more_seeds`` the highway-env and SUMO parts are computed again at those rollout seeds, and their rows give
the mean over the seeds (which is judged) and the range. The report is ``scorecard.json`` and
``scorecard.md`` (one column per checkpoint, every row against its target)."""

from __future__ import annotations

import functools
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from trajeglish_env.file_digest import file_sha256, source_digest
from trajeglish_env.scenario_io import atomic_path
from trajeglish_env.scorecard_speed import speed_part

FORMAT = 1  # of the saved parts: a part saved by another format is computed again
PARTS = ("highway", "sumo", "sumo_partial", "womd", "brake", "long", "demo", "tokenize", "speed")
# the parts whose model-alone rows move with the rollout seed by more than candidates differ
# (docs/evaluation.md, "How far the scorecard's rows move with the rollout seed alone"): `more_seeds` computes
# them again
SEEDED_PARTS = ("highway", "sumo")
SCORES = ("metametric", "collision_rate", "offroad_rate", "traffic_light_violation_rate", "min_ade")


def vehicle_standing(by_kind: dict[str, dict[str, dict[str, int]]]) -> float | None:
    """Share of vehicle agent-steps standing over every scene kind of ``evaluate``'s ``standing_by_kind``
    (None: no vehicle steps)."""
    counts = [c["vehicle"] for c in by_kind.values() if "vehicle" in c]
    steps = sum(c["steps"] for c in counts)
    return sum(c["standing"] for c in counts) / steps if steps else None


@dataclass(frozen=True)
class SceneSet:
    """Held-out scenes ``trajeglish generate --source SOURCE --scenes SCENES --seed SEED`` makes."""

    source: str
    scenes: int
    seed: int

    @property
    def folder(self) -> str:
        return f"{self.source}_{self.scenes}_seed{self.seed}"

    def command(self) -> str:
        return f"trajeglish generate --source {self.source} --scenes {self.scenes} --seed {self.seed}"


@dataclass(frozen=True)
class ScorecardConfig:
    """The held-out sets and sizes of the issue's tables (defaults: its targets' settings): 8 rollouts of
    8 s per scene at the env's default NPC settings, partial control on >= 32 scenes of each source, 16
    rollouts of the shared WOMD scene, 40 brake-test episodes, 2 rollouts of 30 s per SUMO scene."""

    highway: SceneSet = SceneSet("highway", 32, 2)
    sumo: SceneSet = SceneSet("sumo", 16, 2)
    sumo_partial: SceneSet = SceneSet("sumo", 32, 2)
    rollouts: int = 8
    womd_rollouts: int = 16
    brake_episodes: int = 40
    long_seconds: float = 30.0
    long_rollouts: int = 2
    seed: int = 0
    more_seeds: tuple[int, ...] = ()  # SEEDED_PARTS again at these rollout seeds: rows show mean and range
    processes: int = 1  # rollout processes of the evaluations (the same rollouts)
    womd: str | None = None  # the WOMD scenario file (None: the shared one, see benchmark.womd)
    speed_batches: tuple[int, ...] = (1, 8)  # env batch sizes timed against the shipped model
    speed_repeats: int = 2  # interleaved pairs per batch size (the machine's speed drifts)
    # each timed env run repeats its window cycle until this long (one cycle at B = 1 lasts about 0.3 s: too
    # short for a rate that holds; stop 74's two pairs of such runs read 1.21x for two models within 3 %)
    speed_min_seconds: float = 2.0
    parts: tuple[str, ...] = PARTS

    def __post_init__(self) -> None:
        unknown = [p for p in self.parts if p not in PARTS]
        if unknown or not self.parts:
            raise ValueError(f"ScorecardConfig.parts: expected some of {PARTS}, got {list(self.parts)}")
        if not self.speed_batches or any(b < 1 for b in self.speed_batches):
            raise ValueError(
                f"ScorecardConfig.speed_batches must be batch sizes >= 1, got {self.speed_batches}"
            )
        if not self.speed_min_seconds >= 0:
            raise ValueError(
                f"ScorecardConfig.speed_min_seconds must be >= 0 s, got {self.speed_min_seconds}"
            )
        for name in (
            "rollouts",
            "womd_rollouts",
            "brake_episodes",
            "long_rollouts",
            "processes",
            "speed_repeats",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ScorecardConfig.{name} must be an int >= 1, got {value!r}")
        seeds = (self.seed, *self.more_seeds)
        if any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seeds) or len(
            set(seeds)
        ) < len(seeds):
            raise ValueError(
                f"ScorecardConfig.more_seeds must be ints >= 0 that differ from each other and from seed "
                f"{self.seed!r}, got {self.more_seeds!r}"
            )
        if not self.long_seconds > 8.0:
            raise ValueError(f"ScorecardConfig.long_seconds must be > 8 (the split), got {self.long_seconds}")


QUICK = ScorecardConfig(
    highway=SceneSet("highway", 2, 2),
    sumo=SceneSet("sumo", 1, 2),
    sumo_partial=SceneSet("sumo", 2, 2),
    rollouts=2,
    womd_rollouts=2,
    brake_episodes=2,
    long_seconds=9.0,
    long_rollouts=1,
    speed_batches=(1,),
    speed_repeats=1,
    speed_min_seconds=0.0,
)  # a smoke run: every part, small


@functools.cache
def code_digest() -> str:
    """This package's :func:`source_digest`: a saved part whose digest differs was computed by other code,
    so its figures may not be today's."""
    return source_digest(Path(__file__).resolve().parent)


@dataclass
class Scorecard:
    """One scorecard run: its ``config``, the folder of generated scenes ``data_dir`` and of results
    ``out``; :meth:`part` computes or reads one part of one checkpoint."""

    config: ScorecardConfig
    out: Path
    data_dir: Path
    progress: bool = True
    log: Callable[[str], None] = field(default=lambda text: print(text, file=sys.stderr))
    tag: str = ""  # suffix of this card's part files and evaluation folders ("@seed3" for a further seed)

    def scenes_of(self, scene_set: SceneSet) -> Path:
        """The folder of ``scene_set``'s scenes, generated (or finished) first."""
        from trajeglish_env.sources.generation import GenerationConfig, generate

        folder = self.data_dir / scene_set.folder
        generate(
            GenerationConfig(scene_set.source, scene_set.scenes, scene_set.seed),
            folder,
            workers=self.config.processes,
            progress=self.progress,
        )
        return folder

    def womd_scenes(self) -> Path | str:
        """The converted shared WOMD scene's folder, or why it is skipped."""
        from trajeglish_env.benchmark.womd import locate_womd
        from trajeglish_env.sources.womd_convert import convert_womd

        found = locate_womd(self.config.womd)
        if isinstance(found, str):
            return found
        folder = self.data_dir / f"womd_{found.stem}"
        if not (folder / "manifest.json").is_file() and not any(folder.glob("*.npz")):
            report = convert_womd([found], folder, self.progress)
            if report.get("failed"):
                return f"{found}: could not be converted: {report['failed']}"
        return folder

    def part(self, name: str, label: str, ckpt: Any) -> dict[str, Any]:
        """Part ``name`` of the checkpoint ``ckpt`` (shown as ``label``): read from its saved file when that
        was made from the same checkpoint file and settings, else computed and saved (a part skipped for
        want of an input is not saved: the next run tries again)."""
        settings = part_settings(self.config, name)
        sha = file_sha256(ckpt.path)
        key = sha[:16]  # the folder of this checkpoint file's parts and outputs
        path = self.out / "parts" / key / f"{name}{self.tag}.json"
        if path.is_file():
            try:
                saved = json.loads(path.read_text())
            except (OSError, ValueError):
                saved = None  # unreadable: computed again (the atomic write never leaves half a file)
            if not isinstance(saved, dict):
                saved = None  # not a part document (edited by hand?): computed again
            if saved and saved.get("format") == FORMAT and saved.get("settings") == settings:
                self.log(f"scorecard: {label} {name}: from {path}")
                return saved["result"]
            if saved and saved.get("settings", {}).get("code") != settings["code"]:
                self.log(f"scorecard: {label} {name}: {path} was computed by other code, computed again")
        self.log(f"scorecard: {label} {name} ...")
        start = time.perf_counter()
        result = PART_FUNCTIONS[name](self, key, ckpt)
        if "skipped" in result:
            self.log(f"scorecard: {label} {name} skipped: {result['skipped']}")
            return result
        result["compute_seconds"] = round(time.perf_counter() - start, 1)
        document = {"format": FORMAT, "checkpoint_sha256": sha, "settings": settings, "result": result}
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(document, indent=1))
        return result


def part_settings(config: ScorecardConfig, name: str) -> dict[str, Any]:
    """The settings a part's result depends on, as plain JSON values (a saved part is reused only when they
    are the same): the scorecard's own, the env's default NPC sampling and the metrics' version (so a
    change of those defaults computes the parts again), the package's code digest and the WOMD file's
    sha256."""
    from trajeglish_env.evaluation import EvalConfig
    from trajeglish_env.sampler.config import SamplingConfig

    common = {
        "seed": config.seed,
        "sampling": asdict(SamplingConfig()),
        "metrics": EvalConfig().metrics,
        "code": code_digest(),
    }
    by_part: dict[str, dict[str, Any]] = {
        "highway": {"scenes": asdict(config.highway), "rollouts": config.rollouts},
        "sumo": {"scenes": asdict(config.sumo), "rollouts": config.rollouts},
        "sumo_partial": {"scenes": asdict(config.sumo_partial), "rollouts": config.rollouts},
        "womd": {"file": _womd_identity(config), "rollouts": config.womd_rollouts},
        "brake": {
            "scenes": [asdict(config.highway), asdict(config.sumo)],
            "test": asdict(brake_config(config)),
        },
        "long": {"scenes": asdict(config.sumo), "config": asdict(long_config(config))},
        "demo": {},
        "tokenize": {},
        "speed": {
            "batches": list(config.speed_batches),
            "repeats": config.speed_repeats,
            "min_seconds": config.speed_min_seconds,
        },
    }
    return json.loads(json.dumps({"part": name, **common, **by_part[name]}, default=str))


def _womd_identity(config: ScorecardConfig) -> str | None:
    """The WOMD file the ``womd`` part reads, by its sha256 (None: none found, the part is skipped)."""
    from trajeglish_env.benchmark.womd import locate_womd

    found = locate_womd(config.womd)
    return None if isinstance(found, str) else file_sha256(found)


def brake_config(config: ScorecardConfig) -> Any:
    """The brake test the ``brake`` part plays: guarded and unguarded model NPCs against IDM."""
    from trajeglish_env.brake_test import BrakeTestConfig

    return BrakeTestConfig(
        npcs=("trajeglish+guard", "trajeglish", "idm"), episodes=config.brake_episodes, seed=config.seed
    )


def long_config(config: ScorecardConfig) -> Any:
    """The ``long`` part's rollouts: guarded (the env's NPCs), ``long_seconds`` past the current step."""
    from trajeglish_env.long_rollouts import LongRolloutConfig

    return LongRolloutConfig(
        seconds=config.long_seconds, rollouts=config.long_rollouts, guards=(True,), seed=config.seed
    )


def _evaluate(
    card: Scorecard,
    key: str,
    ckpt: Any,
    data: Path,
    scenes: int,
    rollouts: int,
    guards: tuple[bool, ...],
    partial: bool,
) -> dict[str, Any]:
    """``trajeglish evaluate`` of one checkpoint, named ``model`` in the methods (``partial``: with partial
    control), kept to the rows' figures (every method's: the log's and constant velocity's set targets)."""
    from trajeglish_env.evaluation import EvalConfig, evaluate
    from trajeglish_env.scorecard_rows import STANDING

    config = EvalConfig(
        rollouts=rollouts,
        scenes=scenes,
        seed=card.config.seed,
        guards=guards,
        rollout_processes=card.config.processes,
    )
    out = card.out / "evaluate" / f"{data.name}_{key}{card.tag}"
    result = evaluate(
        data, {"model": ckpt}, config, out, partial="model" if partial else None, progress=card.progress
    )
    figures = {
        "scenes": result["scenes"],
        "rollouts": rollouts,
        "methods": {
            method: {**{k: r["scores"][k] for k in SCORES}, STANDING: vehicle_standing(r["standing_by_kind"])}
            for method, r in result["methods"].items()
        },
        "report": result["markdown"],
    }
    if partial:
        figures["partial_control"] = {p: result["partial_control"][p] for p in ("first", "last")}
    return figures


def _source_part(
    scene_set: Callable[[ScorecardConfig], SceneSet], guards: tuple[bool, ...], partial: bool
) -> Callable[[Scorecard, str, Any], dict[str, Any]]:
    """The part that evaluates a checkpoint on one held-out scene set."""

    def part(card: Scorecard, key: str, ckpt: Any) -> dict[str, Any]:
        chosen = scene_set(card.config)
        data = card.scenes_of(chosen)
        return _evaluate(card, key, ckpt, data, chosen.scenes, card.config.rollouts, guards, partial)

    return part


def _womd_part(card: Scorecard, key: str, ckpt: Any) -> dict[str, Any]:
    data = card.womd_scenes()
    if isinstance(data, str):
        return {"skipped": data}
    return _evaluate(card, key, ckpt, data, 1, card.config.womd_rollouts, (False, True), partial=False)


def _brake_part(card: Scorecard, key: str, ckpt: Any) -> dict[str, Any]:
    from trajeglish_env.brake_test import brake_test
    from trajeglish_env.training.dataset import SceneStore

    folders = [card.scenes_of(card.config.highway), card.scenes_of(card.config.sumo)]
    scenes = list(SceneStore(folders).scenes)
    config = brake_config(card.config)
    result = brake_test(scenes, config, ckpt, card.out / "brake" / key, progress=card.progress)
    return {"candidates": result["candidates"], "npcs": result["npcs"]}


def _long_part(card: Scorecard, key: str, ckpt: Any) -> dict[str, Any]:
    from trajeglish_env.long_rollouts import long_rollout_rates
    from trajeglish_env.training.dataset import SceneStore

    scenes = list(SceneStore(card.scenes_of(card.config.sumo)).scenes)
    result = long_rollout_rates(ckpt, scenes, long_config(card.config), progress=card.progress)
    method = result["methods"]["trajeglish+guard"]
    return {
        "scenes": result["scenes"],
        "seconds": result["seconds"],
        "split_s": result["split_s"],
        **{
            event: {k: method[event][k] for k in ("before", "after", "ratio")}
            for event in ("collision", "offroad")
        },
    }


def _demo_part(card: Scorecard, key: str, ckpt: Any) -> dict[str, Any]:
    from trajeglish_env.env.demo import run_demo

    result = run_demo(card.out / "demo" / key, checkpoint=str(ckpt.path), progress=False)
    keys = (
        "scene",
        "npcs",
        "steps",
        "npc_collision_rate",
        "npc_offroad_rate",
        "ego_collision_steps",
        "video",
    )
    return {k: result[k] for k in keys}


def _tokenize_part(card: Scorecard, key: str, ckpt: Any) -> dict[str, Any]:
    """The largest error of the checkpoint's vocabulary tokenizing each class's tracks at the edges of its
    motion limits (the env's vehicle limits, reversing included)."""
    from trajeglish_env.scenario import AgentKind
    from trajeglish_env.tokenizer.coverage import stress_error

    return {
        "vocab_size": ckpt.vocabulary.size,
        "max_cm": {k.name.lower(): round(100 * stress_error(ckpt.vocabulary, k, 0.1), 2) for k in AgentKind},
    }


PART_FUNCTIONS: dict[str, Callable[[Scorecard, str, Any], dict[str, Any]]] = {
    "highway": _source_part(lambda c: c.highway, (False, True), partial=True),
    "sumo": _source_part(lambda c: c.sumo, (False, True), partial=False),
    "sumo_partial": _source_part(lambda c: c.sumo_partial, (True,), partial=True),
    "womd": _womd_part,
    "brake": _brake_part,
    "long": _long_part,
    "demo": _demo_part,
    "tokenize": _tokenize_part,
    "speed": speed_part,
}


def _parts(card: Scorecard, label: str, ckpt: Any) -> dict[str, Any]:
    """Every configured part of one checkpoint, then :data:`SEEDED_PARTS` at each of ``more_seeds``
    (keyed ``NAME@seedS``, saved apart)."""
    parts = {name: card.part(name, label, ckpt) for name in card.config.parts}
    for seed in card.config.more_seeds:
        again = replace(card, config=replace(card.config, seed=seed, more_seeds=()), tag=f"@seed{seed}")
        for name in SEEDED_PARTS:
            if name in card.config.parts:
                parts[f"{name}{again.tag}"] = again.part(name, label, ckpt)
    return parts


def run_scorecard(
    checkpoints: dict[str, Any],
    config: ScorecardConfig = ScorecardConfig(),
    out: str | os.PathLike[str] = "out/scorecard",
    data_dir: str | os.PathLike[str] | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Every configured part of every checkpoint (``{label: Checkpoint}``, each loaded from a file), then
    the rows against their targets; writes ``scorecard.json`` and ``scorecard.md`` into ``out``."""
    from trajeglish_env.scorecard_rows import markdown, target_rows

    if not checkpoints:
        raise ValueError("scorecard: no checkpoint to score")
    if config.womd is not None and "womd" in config.parts and not Path(config.womd).is_file():
        raise ValueError(f"scorecard --womd {config.womd}: no such WOMD scenario file")
    bad = [label for label in checkpoints if not label or any(c in label for c in "/\\|`\n")]
    if bad:
        raise ValueError(f"scorecard: checkpoint names {bad} may not be empty or hold / \\ | ` or newlines")
    missing = [label for label, ckpt in checkpoints.items() if ckpt.path is None]
    if missing:
        raise ValueError(
            f"scorecard: checkpoints {missing} were not loaded from a file (their rows are keyed by it)"
        )
    out = Path(out)
    card = Scorecard(config, out, Path(data_dir) if data_dir else out / "data", progress)
    parts = {label: _parts(card, label, ckpt) for label, ckpt in checkpoints.items()}
    rows = {label: target_rows(p) for label, p in parts.items()}
    result = {
        "checkpoints": {label: str(ckpt.path) for label, ckpt in checkpoints.items()},
        "config": asdict(replace(config, parts=tuple(config.parts))),
        "scene_sets": {name: getattr(config, name).command() for name in ("highway", "sumo", "sumo_partial")},
        "parts": parts,
        "rows": rows,
        "met": {label: sum(1 for r in rs if r["met"]) for label, rs in rows.items()},
        "rows_with_a_target": {
            label: sum(1 for r in rs if r["met"] is not None) for label, rs in rows.items()
        },
    }
    text = markdown(result)
    with atomic_path(out / "scorecard.json") as tmp:
        tmp.write_text(json.dumps(result, indent=2))
    with atomic_path(out / "scorecard.md") as tmp:
        tmp.write_text(text)
    result["markdown"] = str(out / "scorecard.md")
    return result
