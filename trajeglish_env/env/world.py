"""The simulation state read by NPC policies, observations and rewards: every agent's states so far, and
who has already moved in the current step (the intra-timestep order)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.batch_geometry import latest_states as batch_latest_states
from trajeglish_env.scenario import Scenario


@dataclass(frozen=True)
class WorldView:
    """Read-only view of the simulation in the middle of step ``t`` (from ``t`` to ``t + 1``).

    ``xyh [N,T,3]`` / ``valid [N,T]``: exact states of every agent for steps ``0 .. t`` and, for agents
    that already ``moved [N]`` this step, ``t + 1`` (log-replayed agents count as moved: their motion is
    fixed in advance). ``external [N]`` / ``npc [N]``: roles. Treat the arrays as read-only.
    """

    scenario: Scenario
    xyh: np.ndarray
    valid: np.ndarray
    t: int
    moved: np.ndarray
    external: np.ndarray
    npc: np.ndarray

    @property
    def dt(self) -> float:
        return float(self.scenario.dt)

    def latest(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each agent's latest decided state ``[N,3]`` (``t + 1`` if it moved, else ``t``), whether it is
        present ``[N]``, and its velocity ``[N,2]`` (m/s, over the step that led to that state)."""
        return latest_states(self.xyh, self.valid, self.t, self.moved, self.dt)


def latest_states(
    xyh: np.ndarray, valid: np.ndarray, t: int, moved: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """See :meth:`WorldView.latest` (vectorized over agents; the formula of
    :func:`~trajeglish_env.batch_geometry.latest_states`)."""
    last = valid.shape[1] - 1
    return batch_latest_states(
        xyh[:, t],
        xyh[:, min(t + 1, last)],
        xyh[:, max(t - 1, 0)],
        valid[:, t],
        valid[:, t + 1] if t < last else np.zeros_like(moved),
        valid[:, max(t - 1, 0)] & (t > 0),
        moved,
        np.asarray(dt),
    )
