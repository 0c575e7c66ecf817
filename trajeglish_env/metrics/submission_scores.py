"""Local WOSAC scores of a submission against converted shards (``trajeglish score-submission``).

The submission (one shard, a ``.tar.gz`` or a directory of shards) is streamed one shard at a time; each
scenario is scored with :func:`~trajeglish_env.metrics.score_rollouts` against its scene, with the raw log
details kept beside the shard (``NAME.details.npz``; official-value parity) and the submitted ``center_z``.
Scenarios are shared over ``torchrun`` ranks by their position in the submission; the merged scores are
the one-process scores. Scenes of the data that the submission lacks are reported (the leaderboard
rejects incomplete submissions).
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from trajeglish_env.distributed import Ranks, gather
from trajeglish_env.metrics.log_details import LogDetails
from trajeglish_env.metrics.log_details_io import details_path, load_log_details
from trajeglish_env.metrics.scoring import RealismScores, mean_scores, score_rollouts
from trajeglish_env.metrics.submission import SubmittedRollouts, iter_submission, submission_files
from trajeglish_env.scenario import Scenario
from trajeglish_env.scenario_io import (
    atomic_path,
    load_scenarios,
    scenario_files,
    scenario_ids,
)

__all__ = [
    "WOSAC_ROLLOUTS",
    "MissingScenarioError",
    "SceneIndex",
    "missing_details_message",
    "score_submission",
    "score_submitted",
]

Paths = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]
WOSAC_ROLLOUTS = 32  # joint rollouts per scenario in a Sim Agents submission


class MissingScenarioError(KeyError, ValueError):
    """A submitted scenario id that the scored data does not hold (bad input: the CLI's one-line error)."""

    def __str__(self) -> str:  # KeyError's own str() would quote the message
        return str(self.args[0])


class SceneIndex:
    """Scenes (and their raw log details) of many shards by scenario id, loading a few shards at a time."""

    def __init__(self, data: Paths, cached_shards: int = 2):
        paths = [data] if isinstance(data, (str, os.PathLike)) else list(data)
        self.files = scenario_files(paths)
        self.where: dict[str, tuple[int, int]] = {}
        for k, f in enumerate(self.files):
            for j, sid in enumerate(scenario_ids(f)):
                if sid in self.where:
                    raise ValueError(
                        f"scenario {sid!r} is in both {self.files[self.where[sid][0]]} and {f}: each "
                        "scenario must be in the data once (the same shard passed twice, or converted twice?)"
                    )
                self.where[sid] = (k, j)
        self._cache: OrderedDict[int, tuple[list[Scenario], list[LogDetails | None]]] = OrderedDict()
        self._size = cached_shards

    def _shard(self, k: int) -> tuple[list[Scenario], list[LogDetails | None]]:
        if k not in self._cache:
            scenes = load_scenarios(self.files[k])
            sidecar = details_path(self.files[k])
            details: list[LogDetails | None] = (
                list(load_log_details(sidecar)) if sidecar.is_file() else [None] * len(scenes)
            )
            self._cache[k] = (scenes, details)
            while len(self._cache) > self._size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(k)
        return self._cache[k]

    def get(self, scenario_id: str) -> tuple[Scenario, LogDetails | None]:
        """The scene with this id and its details (None for scenes without a details file; a WOMD scene
        without them is an error: its scores would silently differ from the official ones)."""
        if scenario_id not in self.where:
            raise MissingScenarioError(
                f"scenario {scenario_id!r} of the submission is not in the data ({len(self.where)} scenes "
                f"in {len(self.files)} files, e.g. {self.files[0]}): pass --data with the scenes it was "
                "sampled on"
            )
        k, j = self.where[scenario_id]
        scenes, details = self._shard(k)
        if details[j] is None and scenes[j].source == "womd":
            raise ValueError(missing_details_message(self.files[k], scenario_id))
        return scenes[j], details[j]


def missing_details_message(shard: str | os.PathLike[str], scenario_id: str) -> str:
    """Why a WOMD scene without its raw log details cannot be scored as the official scorer does."""
    return (
        f"{shard}: scene {scenario_id!r} comes from WOMD but {details_path(shard)} is missing: its raw "
        "log details (the z values and box heights of the log) are needed for scores that match the "
        "official ones (without them minADE alone is off by metres); convert the TFRecord again with "
        "`trajeglish convert-womd`, which writes both files"
    )


def score_submitted(
    item: SubmittedRollouts, scene: Scenario, details: LogDetails | None, config: str = "2025"
) -> RealismScores:
    """The scores of one submitted scenario (its z included) against its scene."""
    return score_rollouts(scene, item.xyh, item.object_id, config, rollouts_z=item.z, details=details)


def score_submission(
    submission: str | os.PathLike[str],
    data: Paths,
    config: str = "2025",
    out: str | os.PathLike[str] | None = None,
    progress: bool = True,
    ranks: Ranks | None = None,
) -> dict[str, Any]:
    """Mean WOSAC scores of a submission over its scenarios (per-scenario scores in ``out`` if given)."""
    start, ranks = time.perf_counter(), ranks or Ranks()
    if out is not None and Path(out).is_dir():  # refused before the scoring work, not after it
        raise IsADirectoryError(
            f"--out {out}: is a directory; give the JSON file to write, e.g. {out}/scores.json"
        )
    submission_files(submission)  # a missing or empty submission fails here, in one line
    index = SceneIndex(data)
    mine: list[tuple[int, RealismScores, int]] = []
    bar = tqdm(desc="score-submission", unit="scenario", file=sys.stderr, disable=not progress)
    for position, item in iter_submission(submission, keep=lambda i: i % ranks.world == ranks.rank):
        scene, details = index.get(item.scenario_id)
        try:
            scored = score_submitted(item, scene, details, config)
        except ValueError as error:
            raise ValueError(f"{submission}: {error}") from error
        mine.append((position, scored, int(item.xyh.shape[0])))
        bar.update(1)
    bar.close()
    merged = sorted((x for part in gather(mine, ranks) for x in part), key=lambda x: x[0])
    scores = [s for _, s, _ in merged]
    if not scores:
        raise ValueError(f"{submission}: no scenarios to score")
    counts = sorted({r for _, _, r in merged})
    if counts != [WOSAC_ROLLOUTS] and ranks.main:  # scored all the same, never silently
        print(
            f"score-submission: warning: {submission} holds {counts} joint rollouts per scenario; WOSAC "
            f"takes exactly {WOSAC_ROLLOUTS}: the leaderboard would reject it, and scores from fewer "
            "rollouts are not comparable",
            file=sys.stderr,
        )
    submitted = {s.scenario_id for s in scores}
    missing = sorted(set(index.where) - submitted)
    result: dict[str, Any] = {
        "submission": str(submission),
        "scenarios": len(scores),
        "missing_count": len(missing),
        "missing": missing[:20],
        "metrics_config": config,
        "rollouts_per_scenario": counts[0] if len(counts) == 1 else counts,
        "scores": mean_scores(scores).to_dict(),
        "processes": ranks.world,
        "seconds": round(time.perf_counter() - start, 2),
    }
    if out is not None and ranks.main:
        with atomic_path(Path(out)) as tmp:
            tmp.write_text(json.dumps({**result, "per_scenario": [s.to_dict() for s in scores]}, indent=2))
        result["out"] = str(out)
    return result
