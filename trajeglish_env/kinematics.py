"""Kinematic limits of a vehicle, shared by the environment's actions and the tokenizer's motion envelope
(the vocabulary must cover every motion the env lets a vehicle make); no dependency on either."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class VehicleLimits:
    """Kinematic bicycle limits of the ``continuous`` action: action[0] in [-1, 1] maps to
    [-max_brake, max_accel] m/s^2 (linearly on each side of 0), action[1] to the front-wheel angle in
    [-s, s] with s = min(max_steer, atan(max_lateral_accel x wheelbase / v^2)) at speed v, the speed before
    the step (tyre grip: full steering is a turn at ``max_lateral_accel`` at most at that speed; speeding
    up under full steering ends a step a little above it, 8.5 m/s^2 for a car); the speed stays in
    [0, max_speed] m/s (no reversing); the wheelbase is ``wheelbase_ratio`` times the agent's length."""

    max_accel: float = 4.0
    max_brake: float = 6.0
    max_steer: float = 0.5
    max_lateral_accel: float = 8.0
    max_speed: float = 40.0
    wheelbase_ratio: float = 0.6

    def steer_limit(self, speed: np.ndarray | float, length: np.ndarray | float) -> np.ndarray:
        """Largest front-wheel angle (rad) at ``speed`` for an agent of ``length``."""
        base = self.wheelbase_ratio * np.asarray(length, dtype=np.float64)
        v2 = np.maximum(np.asarray(speed, dtype=np.float64), 1.0) ** 2
        return np.minimum(self.max_steer, np.arctan(self.max_lateral_accel * base / v2))

    def __post_init__(self) -> None:
        for f in fields(self):
            if not getattr(self, f.name) > 0:
                raise ValueError(f"VehicleLimits.{f.name} must be > 0, got {getattr(self, f.name)}")


def bicycle_local_step(
    speed: np.ndarray,
    accel: np.ndarray,
    steer_fraction: np.ndarray,
    length: float,
    limits: VehicleLimits,
    dt: float,
) -> np.ndarray:
    """``[...,3]`` local (dx, dy, dh) of one step of the env's kinematic bicycle (``continuous`` action,
    ``env.actions.bicycle_step``) from ``speed`` with acceleration ``accel`` m/s^2 and ``steer_fraction``
    of the steering limit: the centre moves at the slip angle ``beta = atan(tan(steer) / 2)`` off the
    heading, so a step carries more sideways motion per heading change than a unicycle's (the
    tokenizer's envelope must cover both)."""
    steer = np.asarray(steer_fraction) * limits.steer_limit(speed, length)
    v_next = np.clip(np.asarray(speed) + np.asarray(accel) * dt, 0.0, limits.max_speed)
    step = (np.asarray(speed) + v_next) / 2 * dt
    beta = np.arctan(np.tan(steer) / 2)
    half_base = limits.wheelbase_ratio * length / 2
    return np.stack(
        np.broadcast_arrays(step * np.cos(beta), step * np.sin(beta), step * np.sin(beta) / half_base), -1
    )
