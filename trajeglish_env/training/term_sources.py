"""Which training scenes the colliding-mass term acts on (``train --collision-sources SRC ...``).

The term teaches moves that keep out of collision courses; on highway-env, whose IDM logs follow closely,
it also teaches gaps the logs do not keep, and the guarded kinematics pay for it (docs/evaluation.md,
stops 51-52). Limiting it to some sources keeps plain likelihood on the others. A model's own rollouts of
a source (``sumo+rollout``) count as that source."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from trajeglish_env.scenario import Scenario
from trajeglish_env.training.dataset import ROLLOUT_SOURCE
from trajeglish_env.training.shard_cache import ShardedScenes


def scene_source_list(scenes: Sequence[Scenario]) -> list[str]:
    """The source of every training scene by index (a shard-cached sequence's from its files' headers)."""
    if isinstance(scenes, ShardedScenes):
        return [source for file_sources in scenes.sources for source in file_sources]
    return [s.source for s in scenes]


def base_source(source: str) -> str:
    """A scene's source without the own-rollout mark (``sumo+rollout`` -> ``sumo``)."""
    return source[: -len(ROLLOUT_SOURCE)] if source.endswith(ROLLOUT_SOURCE) else source


def collision_scenes(sources: Sequence[str], wanted: Sequence[str]) -> np.ndarray | None:
    """``[N]`` whether the term acts on each scene (None: ``wanted`` empty, every scene). A wanted source
    that no training scene has is an error: a typo would otherwise switch the term off."""
    if not wanted:
        return None
    bases = np.array([base_source(s) for s in sources], dtype=object)
    present = sorted(set(bases.tolist()))
    missing = [w for w in wanted if w not in present]
    if missing:
        raise ValueError(
            f"--collision-sources {' '.join(missing)}: no training scene has that source; "
            f"the sources there: {', '.join(present)}"
        )
    return np.isin(bases, list(wanted))
