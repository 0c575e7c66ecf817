"""Smooth random trajectories with sensor-like noise, for tokenizer tests and benchmarks (no simulator)."""

from __future__ import annotations

import numpy as np

from trajeglish_env.scenario import AgentKind

# Per class: (speed range m/s, max |yaw rate| rad/s, mean length, mean width).
_PROFILE = {
    AgentKind.VEHICLE: ((0.0, 30.0), 0.35, 4.6, 1.9),
    AgentKind.PEDESTRIAN: ((0.0, 1.8), 1.0, 0.6, 0.6),
    AgentKind.CYCLIST: ((1.0, 8.0), 0.6, 1.8, 0.7),
}


def synthetic_trajectories(
    num_agents: int,
    steps: int,
    rng: np.random.Generator,
    *,
    dt: float = 0.1,
    kinds: tuple[AgentKind, ...] = (AgentKind.VEHICLE,),
    position_noise: float = 0.01,
    heading_noise: float = 0.003,
    max_speed: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(xyh [N,T,3], valid [N,T], size [N,2], kind [N])`` of unicycle agents with smooth speed and yaw rate.

    ``max_speed`` (m/s) caps every class's speed range.
    """
    kind = rng.choice(np.asarray([int(k) for k in kinds]), num_agents)
    cap = np.inf if max_speed is None else max_speed
    lo = np.array([min(_PROFILE[AgentKind(k)][0][0], cap) for k in kind])
    hi = np.array([min(_PROFILE[AgentKind(k)][0][1], cap) for k in kind])
    max_yaw = np.array([_PROFILE[AgentKind(k)][1] for k in kind])
    base_size = np.array([_PROFILE[AgentKind(k)][2:] for k in kind])
    size = base_size * rng.uniform(0.85, 1.25, (num_agents, 2))
    # Smooth profiles: a random start value plus integrated, low-pass filtered random accelerations.
    speed0 = rng.uniform(lo, hi)
    accel = np.cumsum(rng.normal(0, 0.4, (num_agents, steps)), 1) * 0.1
    speed = np.clip(speed0[:, None] + np.cumsum(accel, 1) * dt, lo[:, None], hi[:, None])
    stopped = rng.random(num_agents) < 0.15  # some agents stand still
    speed[stopped] = 0.0
    yaw_rate = max_yaw[:, None] * np.sin(
        rng.uniform(0, 2 * np.pi, (num_agents, 1))
        + np.arange(steps) * dt * rng.uniform(0.1, 0.6, (num_agents, 1))
    )
    yaw_rate *= rng.random((num_agents, 1)) < 0.5  # half drive straight
    heading = rng.uniform(-np.pi, np.pi, (num_agents, 1)) + np.cumsum(yaw_rate * dt, 1)
    step = speed * dt
    x = rng.uniform(-200, 200, (num_agents, 1)) + np.cumsum(step * np.cos(heading), 1)
    y = rng.uniform(-200, 200, (num_agents, 1)) + np.cumsum(step * np.sin(heading), 1)
    xyh = np.stack([x, y, heading], -1)
    moving = ~stopped[:, None, None]
    xyh[..., :2] += rng.normal(0, position_noise, (num_agents, steps, 2)) * moving
    xyh[..., 2] += rng.normal(0, heading_noise, (num_agents, steps)) * moving[..., 0]
    xyh[..., 2] = (xyh[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return xyh, np.ones((num_agents, steps), dtype=bool), size, kind.astype(np.int8)
