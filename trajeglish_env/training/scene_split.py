"""The scenes a training run learns from and validates on: all in memory or shard-cached, validation
from ``--val-data`` or held out of the training data (every k-th scene or shard), and a warning when the
validation scenes are training scenes too (a validation NLL that is not held out)."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from trajeglish_env.scenario import Scenario
from trajeglish_env.scenario_io import load_scenarios
from trajeglish_env.training.dataset import SceneStore
from trajeglish_env.training.shard_cache import ShardedScenes, split_shards


def split_scenes(scenes: Sequence[Scenario], fraction: float) -> tuple[list[Scenario], list[Scenario]]:
    """Deterministic train/validation split: every k-th scene goes to validation."""
    if fraction <= 0 or len(scenes) < 2:
        return list(scenes), []
    k = max(2, round(1 / fraction))
    return [s for i, s in enumerate(scenes) if i % k], [s for i, s in enumerate(scenes) if not i % k]


def training_scenes(
    data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    val_data: str | os.PathLike[str] | None,
    val_fraction: float,
    shard_cache: int,
    val_windows: int,
) -> tuple[Sequence[Scenario], list[Scenario]]:
    """Training and validation scenes: all in memory, or (``shard_cache``) a shard-cached sequence and the
    first ``val_windows`` scenes of the validation shards (every k-th shard unless ``val_data``)."""
    if shard_cache <= 0:
        scenes = SceneStore(data).scenes
        if val_data is not None:
            return scenes, SceneStore(val_data).scenes
        return split_scenes(scenes, val_fraction)
    files = SceneStore(data).files
    if val_data is not None:
        train_files, val_files = files, SceneStore(val_data).files
    else:
        train_files, val_files = split_shards(files, val_fraction)
    val: list[Scenario] = []
    for file in val_files:
        if len(val) >= val_windows:
            break
        val.extend(load_scenarios(file)[: val_windows - len(val)])
    return ShardedScenes(train_files, shard_cache), val


def warn_overlap(train: Sequence[Scenario], val: Sequence[Scenario]) -> None:
    """Warn (stderr) when validation scenes are also training scenes, by scenario id (the same folder
    given twice, or a copy of it): their NLL is then no held-out figure."""
    if not val:
        return
    ids = train.scenario_ids() if isinstance(train, ShardedScenes) else {s.scenario_id for s in train}
    shared = sorted({s.scenario_id for s in val} & set(ids))
    if shared:
        print(
            f"train: warning: {len(shared)} of the {len(val)} validation scenes ({', '.join(shared[:3])}) "
            "are training scenes too: the validation NLL is not held out; pass --val-data with other scenes",
            file=sys.stderr,
        )
