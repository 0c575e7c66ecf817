"""One env slot's stream of episodes: Gymnasium-style seeding, the scene of each episode (the ``scene``
reset option or a draw) and each episode's own random generator, so that a scene of a batched env plays
exactly what a separate env reset with the same seed plays. A seeded reset's episode depends on the seed and
the scene's id only (:func:`~trajeglish_env.scenario.scenario_seed`): the same in an env holding that scene
alone as in one holding it among others."""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np
from gymnasium.utils import seeding

from trajeglish_env.env.scenes import SceneSet, scene_index
from trajeglish_env.scenario import Scenario, scenario_seed
from trajeglish_env.user_warnings import warn_at_caller

RESET_OPTIONS = ("scene",)  # the keys reset(options=...) reads


class EpisodeStream:
    """Seeded by ``next(seed=...)``; without a seed it goes on with its stream (autoresets)."""

    def __init__(self, scenes: SceneSet):
        self.scenes = scenes
        self.np_random, _ = seeding.np_random(None)

    def next(self, seed: int | None, options: dict[str, Any] | None) -> tuple[Scenario, np.random.Generator]:
        """The next episode's scenario and random generator (``options["scene"]``: index or scenario_id; the
        episode a seed plays on a scene is the same whether the scene is named or drawn).
        Other keys are allowed, as PettingZoo's and Gymnasium's conventions (and their API tests) want, but
        each is named in a warning: a misspelt ``"scene"`` must not pass unnoticed."""
        unknown = sorted(str(k) for k in (options or {}) if k not in RESET_OPTIONS)
        if unknown:
            warn_at_caller(
                f"reset options: {', '.join(map(repr, unknown))} ignored; the env reads only "
                f"{', '.join(map(repr, RESET_OPTIONS))} (a scene index or scenario_id)"
            )
        if seed is not None:
            if isinstance(seed, numbers.Integral) and not isinstance(seed, bool):
                seed = int(seed)  # numpy integers, as the batched envs take them
            self.np_random, _ = seeding.np_random(seed)
        chosen = scene_index((options or {}).get("scene"), self.scenes)
        drawn = int(self.np_random.integers(len(self.scenes)))  # drawn either way: a named scene plays
        index = drawn if chosen is None else chosen  # the episode the seed plays when it draws that scene
        scenario = self.scenes.get(index)
        follow_on = int(self.np_random.integers(2**63 - 1))  # autoresets go on with the stream
        own = follow_on if seed is None else scenario_seed(seed, scenario.scenario_id)
        return scenario, np.random.default_rng(own)
