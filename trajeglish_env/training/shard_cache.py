"""Training over any number of shards with memory bounded by a shard cache (``train --shard-cache K``).

:class:`ShardedScenes` is a sequence of every scene of many shard files that keeps at most ``K`` shards
loaded (per data-loading process); only the shards' headers are read up front. :class:`ShardBlockOrder`
draws the scenes of an epoch so that consecutive samples come from ``K`` shards at a time: the shards are
shuffled, cut into blocks of ``K``, and the scenes of each block are shuffled together (a shuffle buffer of
K shards). A batch therefore touches only cached shards, and every scene is still seen once per epoch.
Like :class:`~trajeglish_env.training.training_data.SampleOrder`, sample ``g`` depends only on
``(seed, g)``: resuming and splitting batches over ranks see exactly the one-process data.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from trajeglish_env.scenario import Scenario
from trajeglish_env.scenario_io import load_scenarios, scenario_files, scenario_ids, scene_sources

__all__ = ["ShardBlockOrder", "ShardedScenes", "split_shards"]


class ShardedScenes(Sequence[Scenario]):
    """Every scene of ``files`` by global index, at most ``cache_shards`` shards in memory at a time."""

    def __init__(self, files: Sequence[str | os.PathLike[str]], cache_shards: int):
        if cache_shards < 1:
            raise ValueError(f"cache_shards must be >= 1, got {cache_shards}")
        self.files = [Path(f) for f in files]
        self.sources = [scene_sources(f) for f in self.files]  # header reads only
        self.counts = np.array([len(s) for s in self.sources], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        self.cache_shards = cache_shards
        self._cache: OrderedDict[int, list[Scenario]] = OrderedDict()

    @classmethod
    def from_paths(cls, paths: Sequence[str | os.PathLike[str]], cache_shards: int) -> ShardedScenes:
        """The scenes of every shard under the given files/directories."""
        files = scenario_files(paths)
        return cls(files, cache_shards)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, index: int) -> Scenario:  # type: ignore[override]
        if not 0 <= index < len(self):
            raise IndexError(f"scene {index} of {len(self)}")
        shard = int(np.searchsorted(self.offsets, index, side="right") - 1)
        return self.shard(shard)[index - int(self.offsets[shard])]

    def shard(self, k: int) -> list[Scenario]:
        """The scenes of shard ``k`` (loaded on first use; the least recently used shard is dropped)."""
        if k not in self._cache:
            self._cache[k] = load_scenarios(self.files[k])
            while len(self._cache) > self.cache_shards:
                self._cache.popitem(last=False)
        self._cache.move_to_end(k)
        return self._cache[k]

    def scenario_ids(self) -> set[str]:
        """Every scene's scenario id (read from the files without loading the scenes)."""
        return {sid for f in self.files for sid in scenario_ids(f)}

    def all_sources(self) -> list[str]:
        """Sorted set of the scenes' sources (from the headers)."""
        return sorted({s for shard in self.sources for s in shard})


MIN_SHARDS_TO_HOLD_OUT = 4  # fewer shards: none is held out (train warns; --val-data gives a held-out set)


def split_shards(files: Sequence[Path], fraction: float) -> tuple[list[Path], list[Path]]:
    """Deterministic train/validation split by whole shards: every k-th shard (k = 1 / ``fraction``) goes to
    validation; with fewer than k shards the first one, where there are at least four (a quarter of the data
    at most; the first of two shards held out half of it), else none."""
    if fraction <= 0 or len(files) < MIN_SHARDS_TO_HOLD_OUT:
        return list(files), []
    k = max(2, round(1 / fraction))
    return [f for i, f in enumerate(files) if i % k], [f for i, f in enumerate(files) if not i % k]


@dataclass(frozen=True)
class ShardBlockOrder:
    """Maps a global sample counter to (epoch, scene index), ``block`` shards at a time (module doc)."""

    counts: tuple[int, ...]
    block: int
    seed: int
    _offsets: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_offsets", np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64))

    @property
    def num_scenes(self) -> int:
        return int(self._offsets[-1])

    def __call__(self, g: int) -> tuple[int, int]:
        epoch, pos = divmod(int(g), self.num_scenes)
        return epoch, int(self._epoch_order(epoch)[pos])

    @lru_cache(maxsize=2)  # noqa: B019 (one order per epoch; the instance lives as long as the run)
    def _epoch_order(self, epoch: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, 11, epoch])
        shards = rng.permutation(len(self.counts))
        order = []
        for first in range(0, len(shards), self.block):
            scenes = np.concatenate(
                [
                    np.arange(self._offsets[k], self._offsets[k + 1])
                    for k in shards[first : first + self.block]
                ]
            )
            order.append(scenes[rng.permutation(len(scenes))])
        return np.concatenate(order)
