"""Kinematic realism features from central differences (WOSAC 2024+, spec §2.1), float32 like the reference.

All functions take trajectories with time on the last axis and return arrays of the same shape, NaN
where a neighbour step is missing (the first and last step; the first two and last two for
accelerations).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "angular_acceleration",
    "angular_speed",
    "central_difference",
    "kinematic_features",
    "linear_acceleration",
    "linear_speed",
    "wrap_angle32",
]

_PI = np.float32(np.pi)
_TWO_PI = np.float32(2.0 * np.pi)


def wrap_angle32(angle: np.ndarray) -> np.ndarray:
    """Wrap radians to [-pi, pi) in float32 with a floor-mod (``wrap(pi) = -pi``)."""
    angle = np.asarray(angle, dtype=np.float32)
    return np.mod(angle + _PI, _TWO_PI) - _PI


def central_difference(values: np.ndarray) -> np.ndarray:
    """``(f[t+1] - f[t-1]) / 2`` along the last axis; NaN at the first and last step."""
    values = np.asarray(values, dtype=np.float32)
    out = np.full(values.shape, np.nan, dtype=np.float32)
    out[..., 1:-1] = (values[..., 2:] - values[..., :-2]) / np.float32(2.0)
    return out


def linear_speed(xyz: np.ndarray, dt: float) -> np.ndarray:
    """Speed magnitude (m/s) ``[..., T]`` of positions ``xyz [..., T, D]`` (D = 2 or 3, z included)."""
    xyz = np.asarray(xyz, dtype=np.float32)
    step = central_difference(np.moveaxis(xyz, -1, 0))  # [D, ..., T]
    return np.sqrt(np.sum(step * step, axis=0)) / np.float32(dt)


def linear_acceleration(speed: np.ndarray, dt: float) -> np.ndarray:
    """Signed change of the speed magnitude (m/s^2), a central difference of ``speed``."""
    return central_difference(speed) / np.float32(dt)


def _angular_step(heading: np.ndarray) -> np.ndarray:
    """Heading change per step (rad), the two-step difference wrapped before halving."""
    return wrap_angle32(np.float32(2.0) * central_difference(heading)) / np.float32(2.0)


def angular_speed(heading: np.ndarray, dt: float) -> np.ndarray:
    """Yaw rate (rad/s) ``[..., T]`` of headings ``[..., T]``."""
    return _angular_step(heading) / np.float32(dt)


def angular_acceleration(heading: np.ndarray, dt: float) -> np.ndarray:
    """Yaw acceleration (rad/s^2) ``[..., T]``: the wrapped central difference of the per-step yaw rate."""
    return _angular_step(_angular_step(heading)) / np.float32(dt * dt)


def kinematic_features(xyz: np.ndarray, heading: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """The four kinematic features ``[..., T]`` (linear/angular speed and acceleration) by name."""
    speed = linear_speed(xyz, dt)
    return {
        "linear_speed": speed,
        "linear_acceleration": linear_acceleration(speed, dt),
        "angular_speed": angular_speed(heading, dt),
        "angular_acceleration": angular_acceleration(heading, dt),
    }
