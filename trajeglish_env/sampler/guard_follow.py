"""The following rule of guarded sampling (``SamplingConfig.guard_follow_decel``, m/s^2): a vehicle or
cyclist may not go faster than lets it still stop behind the box ahead of it braking at that deceleration,
whatever that box does next -- its step may not exceed

    v dt  with  v^2 / (2 b) + v dt <= gap - FOLLOW_GAP + v_ahead^2 / (2 b),

``gap`` the distance from its front to the back of the nearest vehicle or cyclist in its path (the path bent
by its last turn) heading its way (within :data:`SAME_WAY` of its heading: a crossing or oncoming box is the
one-step collision rule's), ``v_ahead`` that box's speed along its heading, ``b`` the deceleration.
Where it is closer than that already, it brakes at the grip limit (:data:`GRIP_BRAKE_STEP`). The cap does
not depend on the candidate, so the guard's lazy passes stay exact.

Why: the collision rule looks one step ahead, so a follower closing on a braking or slower ego held its
speed to the last step and then stopped from 19 m/s in 0.1 s (-186 m/s^2, the ego-evaluation audit of stop
82): no rear-end, but no driver either."""

from __future__ import annotations

import numpy as np

from trajeglish_env.compiled import pair_compiled

STEP_SECONDS = 0.1  # the model's step: every scene source samples at 10 Hz (Scenario.dt)
FOLLOW_GAP = 1.0  # metres a follower keeps behind the box ahead at a standstill (the collision rule: 0)
FOLLOW_SIDE = 0.25  # metres beyond the half widths' sum within which a box counts as in the path
FOLLOW_SLACK = 0.02  # metres a step's forward move may exceed the cap by (the standstill templates move less)
SAME_WAY = np.deg2rad(45.0)  # a box ahead heading within this of the rider's heading is followed
MAX_CURVATURE = 0.2  # 1/m: the path bends at most this much (a 5 m radius)
# metres a step's forward move may shrink by when braking at the env's grip limit (8.5 m/s^2 x 0.1 s x 0.1 s)
GRIP_BRAKE_STEP = 0.085


def follow_caps(
    origin: np.ndarray,
    size: np.ndarray,
    pace: np.ndarray,
    turn: np.ndarray,
    state: np.ndarray,
    sizes: np.ndarray,
    present: np.ndarray,
    velocity: np.ndarray,
    riders: np.ndarray,
    decel: float,
) -> np.ndarray:
    """``[n]`` the longest forward step (m) allowed to n riders at ``origin [n,3]`` (boxes ``size [n,2]``,
    last forward step ``pace [n]``, NaN unknown, last heading change ``turn [n]``) among the boxes at
    ``state [n,N,3]`` (``sizes [n,N,2]``, ``present [n,N]``, each rider's own box not present; ``riders
    [n,N]``: vehicles and cyclists) moving at ``velocity [n,N,2]`` m/s, braking at ``decel`` m/s^2; inf
    where no box is followed (compiled where numba is available: :mod:`~trajeglish_env.pair_kernels`)."""
    kernels = pair_compiled()
    if kernels is not None:
        out = np.empty(len(origin))
        floats = (np.ascontiguousarray(a, np.float64) for a in (origin, size, pace, turn, state, sizes))
        kernels.follow_caps(*floats, present, np.ascontiguousarray(velocity, np.float64), riders, decel, out)
        return out
    dt = STEP_SECONDS
    c, s = np.cos(origin[:, 2])[:, None], np.sin(origin[:, 2])[:, None]
    dx, dy = state[..., 0] - origin[:, None, 0], state[..., 1] - origin[:, None, 1]
    along, across = dx * c + dy * s, dy * c - dx * s
    with np.errstate(invalid="ignore", divide="ignore"):
        curvature = np.clip(np.nan_to_num(turn / np.maximum(pace, 0.05)), -MAX_CURVATURE, MAX_CURVATURE)
    off_path = np.abs(across - curvature[:, None] * along * along / 2)
    same_way = np.cos(state[..., 2] - origin[:, None, 2]) > np.cos(SAME_WAY)
    in_path = off_path < (size[:, 1, None] + sizes[..., 1]) / 2 + FOLLOW_SIDE
    ahead = present & riders & same_way & (along > 0) & in_path
    gap = along - (size[:, 0, None] + sizes[..., 0]) / 2
    v_ahead = np.maximum(velocity[..., 0] * c + velocity[..., 1] * s, 0.0)
    budget = gap - FOLLOW_GAP + v_ahead * v_ahead / (2 * decel)
    speed = decel * (np.sqrt(dt * dt + 2 * np.maximum(budget, 0.0) / decel) - dt)
    cap = np.where(ahead, speed * dt, np.inf).min(axis=1, initial=np.inf)
    floor = np.where(np.isnan(pace), 0.0, pace - GRIP_BRAKE_STEP)  # too close already: brake at the limit
    return np.where(np.isfinite(cap), np.maximum(cap, floor), np.inf)
