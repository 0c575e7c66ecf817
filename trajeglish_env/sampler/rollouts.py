"""Closed-loop rollouts of one scene: full or partial control, any scene size (spatial/temporal sliding
window)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.scenario import Scenario


@dataclass(frozen=True)
class Rollouts:
    """``xyh [R,N,T,3]`` and ``valid [R,N,T]`` for steps ``0 .. current+horizon`` (history included),
    ``tokens [R,N,T-1]``, which agents the model ``controlled [N]``, and the ``current_index``."""

    xyh: np.ndarray
    valid: np.ndarray
    tokens: np.ndarray
    controlled: np.ndarray
    current_index: int

    @property
    def future(self) -> slice:
        return slice(self.current_index + 1, self.xyh.shape[2])


def rollout(
    ckpt: Checkpoint,
    scenario: Scenario,
    rollouts: int = 1,
    horizon: int = 80,
    controlled: np.ndarray | None = None,
    current_index: int | None = None,
    priority: np.ndarray | None = None,
    config: SamplingConfig | None = None,
) -> Rollouts:
    """Sample ``rollouts`` futures of ``horizon`` steps after ``current_index`` (default: the scene's).

    ``controlled [N]`` bool: agents the model drives (default: every agent valid at the current step);
    all others replay the log. ``priority [N]``: lower acts earlier within a timestep (default: the sdc
    first, then by distance to each subset's centre agent). Same seed, same rollout.
    """
    scenario.validate()  # a user's scene enters here: fail on its field, not deep inside the engine
    current = scenario.current_index if current_index is None else int(current_index)
    if controlled is None:
        controlled = scenario.valid[:, current].copy()
    if priority is None:
        priority = np.zeros(scenario.num_agents)
        priority[scenario.sdc] = -1.0
    engine = RolloutEngine(
        ckpt,
        scenario,
        rollouts,
        horizon,
        np.asarray(controlled, dtype=bool),
        current_index=current,
        priority=priority,
        config=config or SamplingConfig(),
    )
    engine.run()
    return Rollouts(engine.xyh, engine.valid, engine.tokens, engine.controlled, current)
