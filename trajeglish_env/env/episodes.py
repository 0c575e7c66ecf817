"""One env slot's stream of episodes: Gymnasium-style seeding, the scene of each episode (the ``scene``
reset option or a draw) and each episode's own random generator, so that a scene of a batched env plays
exactly what a separate env reset with the same seed plays."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.utils import seeding

from trajeglish_env.env.scenes import SceneSet, scene_index
from trajeglish_env.scenario import Scenario


class EpisodeStream:
    """Seeded by ``next(seed=...)``; without a seed it goes on with its stream (autoresets)."""

    def __init__(self, scenes: SceneSet):
        self.scenes = scenes
        self.np_random, _ = seeding.np_random(None)

    def next(self, seed: int | None, options: dict[str, Any] | None) -> tuple[Scenario, np.random.Generator]:
        """The next episode's scenario and random generator (``options["scene"]``: index or scenario_id;
        other options are ignored)."""
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        index = scene_index((options or {}).get("scene"), self.scenes)  # the only option read
        if index is None:
            index = int(self.np_random.integers(len(self.scenes)))
        scenario = self.scenes.get(index)
        return scenario, np.random.default_rng(int(self.np_random.integers(2**63 - 1)))
