"""What the guard builds once per scene object its engine's rows hold (signals, lane directions), keyed by
the object: a scene loaded again is another object, so the cache is bounded and cleared when full."""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

from trajeglish_env.scenario import Scenario

T = TypeVar("T")


class SceneCache(Generic[T]):
    """``build(scene)`` of each scene object asked for, kept for at most ``limit`` scenes."""

    def __init__(self, build: Callable[[Scenario], T | None], limit: int) -> None:
        self._build, self._limit = build, int(limit)
        self._hits: dict[int, tuple[Scenario, T | None]] = {}

    def get(self, sc: Scenario) -> T | None:
        hit = self._hits.get(id(sc))
        if hit is None or hit[0] is not sc:
            if len(self._hits) >= self._limit:
                self._hits.clear()
            hit = self._hits[id(sc)] = (sc, self._build(sc))
        return hit[1]
