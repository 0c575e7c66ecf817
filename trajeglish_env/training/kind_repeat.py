"""Scene kinds drawn more often in training (``train --repeat KIND=N``): a run's data mix without
generating more scenes of a kind, e.g. SUMO's share on a GPU machine where only highway-env scenes can be
generated, or the roundabouts where the model drives worst (docs/evaluation.md, "Where the NPCs fail").

A key is a scene kind of :func:`~trajeglish_env.scenario.scene_kind` (``highway/roundabout``) or a source
(``sumo``: every kind of it); a scene takes the count of the longest key that matches it, 1 without one.
Each epoch then holds every scene ``count`` times in one fresh permutation, and each copy draws its own
window (frame agent, start step, agent order, noisy tokens), so the data still depends only on
(seed, step): resuming and splitting a batch over processes give what one process would have seen.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from trajeglish_env.scenario import Scenario, scene_kind
from trajeglish_env.training.shard_cache import ShardBlockOrder, ShardedScenes

MAX_REPEAT = 100


def parse_repeat(items: Sequence[str]) -> tuple[tuple[str, int], ...]:
    """``("sumo=2", "highway/roundabout=3")`` -> ``(("highway/roundabout", 3), ("sumo", 2))`` (sorted, so
    the same request is the same config), checked: ``KIND=N`` with 1 <= N <= MAX_REPEAT, each kind once."""
    out: dict[str, int] = {}
    for item in items:
        kind, sep, count = item.partition("=")
        if not sep or not kind or not count.isdigit() or not 1 <= int(count) <= MAX_REPEAT:
            raise ValueError(
                f"--repeat {item!r}: expected KIND=N with N a whole number from 1 to {MAX_REPEAT} "
                "(KIND a scene kind such as highway/roundabout, or a source such as sumo)"
            )
        if kind in out:
            raise ValueError(f"--repeat: {kind!r} is given twice")
        out[kind] = int(count)
    return tuple(sorted(out.items()))


def repeat_counts(scenes: Sequence[Scenario], repeat: tuple[tuple[str, int], ...]) -> np.ndarray:
    """``[N]`` how many times each scene is drawn per epoch; a key that matches no scene is an error (a
    typo would otherwise change nothing)."""
    kinds = [scene_kind(s) for s in scenes]
    counts = np.ones(len(scenes), dtype=np.int64)
    best = np.zeros(len(scenes), dtype=np.int64)  # length of the key that set each count
    for key, n in repeat:
        hit = np.array([k == key or k.startswith(key + "/") for k in kinds], dtype=bool)
        if not hit.any():
            raise ValueError(
                f"--repeat {key}={n}: no training scene is of kind {key!r}; "
                f"the kinds there: {', '.join(sorted(set(kinds)))}"
            )
        take = hit & (len(key) > best)
        counts[take], best[take] = n, len(key)
    return counts


@dataclass(frozen=True)
class RepeatedOrder:
    """Maps a global sample counter to (draw key, scene index): every scene ``counts[i]`` times in a fresh
    permutation per epoch; the draw key (epoch and copy) seeds the copy's window."""

    counts: tuple[int, ...]
    seed: int
    _slots: np.ndarray = field(init=False, repr=False, compare=False)
    _first: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        counts = np.asarray(self.counts, dtype=np.int64)
        object.__setattr__(self, "_slots", np.repeat(np.arange(len(counts)), counts))
        object.__setattr__(self, "_first", np.concatenate([[0], np.cumsum(counts)[:-1]]))

    def __call__(self, g: int) -> tuple[int, int]:
        epoch, pos = divmod(int(g), len(self._slots))
        slot = int(np.random.default_rng([self.seed, 7, epoch]).permutation(len(self._slots))[pos])
        scene = int(self._slots[slot])
        return epoch * MAX_REPEAT + slot - int(self._first[scene]), scene


def window_order(
    scenes: Sequence[Scenario], repeat: tuple[tuple[str, int], ...], shard_cache: int, seed: int
) -> Callable[[int], tuple[int, int]] | None:
    """A run's sample order: shard blocks for shard-cached scenes, ``repeat``'s over in-memory ones, or
    None (the plain per-epoch permutation)."""
    if isinstance(scenes, ShardedScenes):
        if repeat:
            raise ValueError("--repeat needs every scene in memory: leave out --shard-cache")
        return ShardBlockOrder(tuple(scenes.counts.tolist()), shard_cache, seed)
    if not repeat:
        return None
    return RepeatedOrder(tuple(repeat_counts(scenes, repeat).tolist()), seed)
