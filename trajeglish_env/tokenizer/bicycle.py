"""The env's kinematic bicycle as part of the vehicle envelope: its one-step transitions and stress tracks.

The ``continuous`` action moves a vehicle as a kinematic bicycle about its box centre, whose velocity
points ``beta = atan(tan(steer) / 2)`` off its heading; a step then carries about ``wheelbase / 2`` m of
sideways motion per radian of heading change, where a unicycle (the lattice of :mod:`coverage`) carries
half the step's length. An ego steering at 10 m/s is off the unicycle surface by up to 11 cm, so a
vocabulary that must track every motion the env allows covers these transitions too, for the car lengths
the env meets (:data:`BICYCLE_LENGTHS`).
"""

from __future__ import annotations

import numpy as np

from trajeglish_env.kinematics import VehicleLimits, bicycle_local_step
from trajeglish_env.tokenizer.coverage import integrate_steps

BICYCLE_LENGTHS = (4.0, 4.8, 5.5)  # m: the wheelbase (and so the sideways motion) scales with the length
STEER_FRACTIONS = 25
SPEED_STEP = 0.25  # m/s


def bicycle_transitions(limits: VehicleLimits, length: float, dt: float) -> np.ndarray:
    """Deterministic one-step transitions ``[M,3]`` over a grid of speed (0 to the limit), acceleration
    (full and half brake and throttle, none) and steering (a share of the speed's limit, both ways)."""
    speed = np.linspace(0.0, limits.max_speed, int(round(limits.max_speed / SPEED_STEP)) + 1)
    accel = np.array([-limits.max_brake, -limits.max_brake / 2, 0.0, limits.max_accel / 2, limits.max_accel])
    v, a, f = np.meshgrid(speed, accel, np.linspace(-1.0, 1.0, STEER_FRACTIONS), indexing="ij")
    steps = bicycle_local_step(v, a, f, length, limits, dt).reshape(-1, 3)
    return np.unique(np.round(steps, 6), axis=0)


def bicycle_stress_tracks(limits: VehicleLimits, length: float, dt: float, steps: int = 50) -> np.ndarray:
    """Tracks ``xyh [M, steps, 3]`` of constant actions at the limits: start speeds 2 m/s apart, full
    brake, none or full throttle, each at the full and half steering limit both ways."""
    starts = np.unique(np.r_[np.arange(0.0, limits.max_speed, 2.0), limits.max_speed])
    accel = np.array([-limits.max_brake, 0.0, limits.max_accel])
    frac = np.array([-1.0, -0.5, 0.5, 1.0])
    v0, a, f = (x.reshape(-1, 1) for x in np.meshgrid(starts, accel, frac, indexing="ij"))
    speed = np.clip(v0 + a * dt * np.arange(steps), 0.0, limits.max_speed)  # [M, steps]
    local = bicycle_local_step(speed[:, :-1], np.diff(speed, axis=1) / dt, f, length, limits, dt)
    return integrate_steps(local)


def bicycle_random_tracks(
    limits: VehicleLimits, lengths: tuple[float, float], dt: float, count: int, seed: int, steps: int = 50
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` tracks ``xyh [count, steps, 3]`` and lengths ``[count]`` of random actions: half keep one
    random (acceleration, steering) action, half draw a new one every step; start speeds and car lengths
    uniform (speed 0 to the limit, length within ``lengths``). Deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    length = rng.uniform(*lengths, count)
    speed = rng.uniform(0.0, limits.max_speed, count)
    held = rng.uniform(-1.0, 1.0, (count, 1, 2))
    action = np.where(
        (np.arange(count) % 2 == 0)[:, None, None], held, rng.uniform(-1.0, 1.0, (count, steps - 1, 2))
    )
    accel = np.where(
        action[..., 0] >= 0, action[..., 0] * limits.max_accel, action[..., 0] * limits.max_brake
    )
    local = np.empty((count, steps - 1, 3))
    for t in range(steps - 1):  # the speed follows the actions: one vectorized step over every track
        local[:, t] = bicycle_local_step(speed, accel[:, t], action[:, t, 1], length, limits, dt)
        speed = np.clip(speed + accel[:, t] * dt, 0.0, limits.max_speed)
    return integrate_steps(local), length
