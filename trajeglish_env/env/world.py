"""The simulation state read by NPC policies, observations and rewards: every agent's states so far, and
who has already moved in the current step (the intra-timestep order)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    """See :meth:`WorldView.latest` (vectorized over agents)."""
    nxt = moved & valid[:, t + 1] if t + 1 < valid.shape[1] else np.zeros_like(moved)
    cur = valid[:, t] & ~moved
    t1 = min(t + 1, valid.shape[1] - 1)
    tp = max(t - 1, 0)
    state = np.where(nxt[:, None], xyh[:, t1], xyh[:, t])
    prev = np.where(nxt[:, None], xyh[:, t], xyh[:, tp])
    prev_ok = np.where(nxt, valid[:, t], valid[:, tp] & (t > 0))
    present = nxt | cur
    velocity = np.where((present & prev_ok)[:, None], (state[:, :2] - prev[:, :2]) / dt, 0.0)
    return state, present, velocity
