"""Action spaces of external agents and how an action becomes the agent's next state.

``continuous``: Box[-1,1]^2 float32 (acceleration, steering) through a kinematic bicycle model about the
box centre (grip-limited steering; limits in :class:`~trajeglish_env.env.config.VehicleLimits`);
``delta``: Box float32 of the local displacement (dx, dy in m, dh in rad) over one step, bounds
:data:`DELTA_LOW` / :data:`DELTA_HIGH`; ``token``: Discrete(V), template ``a`` of the agent's class in the
motion vocabulary, applied to its exact state. :func:`action_towards` inverts each of them (the action
that best reaches a given state).
"""

from __future__ import annotations

import functools
import zlib
from dataclasses import replace

import numpy as np
from gymnasium import spaces

from trajeglish_env.env.config import VehicleLimits
from trajeglish_env.geometry import to_global, to_local, wrap_angle
from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer.coverage import DEFAULT_ENVELOPES

NON_VEHICLES = (AgentKind.PEDESTRIAN, AgentKind.CYCLIST)  # in kind order after VEHICLE = 0

DELTA_LOW = np.array([-1.0, -1.0, -0.6], dtype=np.float32)  # m, m, rad per 0.1 s step
DELTA_HIGH = np.array([5.0, 1.0, 0.6], dtype=np.float32)
STEERING_CANDIDATES = 201  # steering values tried by action_towards (continuous)


def make_action_space(action_type: str, vocab_size: int) -> spaces.Space:
    """The (per-agent) action space of an action type."""
    if action_type == "continuous":
        return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    if action_type == "delta":
        return spaces.Box(DELTA_LOW, DELTA_HIGH, dtype=np.float32)
    if action_type == "token":
        return spaces.Discrete(int(vocab_size))
    raise ValueError(f"unknown action type {action_type!r}")


def named_action_space(action_type: str, vocab_size: int, agent: str) -> spaces.Space:
    """An agent's own action space object, its sampling seeded from the agent's name (reproducible)."""
    space = make_action_space(action_type, vocab_size)
    space.seed(zlib.crc32(agent.encode()))
    return space


def check_action(space: spaces.Space, action: object, agent: str) -> np.ndarray | int:
    """``action`` as an array (Box) or int (Discrete); a ValueError naming the agent if it is outside."""
    if isinstance(space, spaces.Discrete):
        ok = isinstance(action, (int, np.integer)) and not isinstance(action, (bool, np.bool_))
        ok = ok or (
            isinstance(action, np.ndarray) and action.shape == () and np.issubdtype(action.dtype, np.integer)
        )
        if not ok:
            shape = f" of shape {np.shape(action)}" if isinstance(action, np.ndarray) else ""
            raise ValueError(
                f"agent {agent}: action {action!r} ({type(action).__name__}{shape}) is not an integer "
                f"scalar; expected an int in [0, {int(space.n)}) ({space})"
            )
        value = int(action)  # type: ignore[arg-type]
        if not 0 <= value < int(space.n):
            raise ValueError(f"agent {agent}: action {value} is outside the action space {space}")
        return value
    assert isinstance(space, spaces.Box)
    if np.iscomplexobj(action):
        raise ValueError(f"agent {agent}: action {action!r} is complex; expected real numbers in {space}")
    try:
        arr = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"agent {agent}: action {action!r} is not numeric; expected {space}") from None
    if arr.shape != space.shape or not np.isfinite(arr).all():
        raise ValueError(
            f"agent {agent}: action {action!r} must be a finite array of shape {space.shape} ({space})"
        )
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)
    tol = 1e-6 * np.maximum(1.0, np.abs(high - low))
    if (arr < low - tol).any() or (arr > high + tol).any():
        raise ValueError(
            f"agent {agent}: action {arr.tolist()} is outside the action space bounds "
            f"low={low.tolist()} high={high.tolist()}"
        )
    return np.clip(arr, low, high)


@functools.lru_cache(maxsize=64)
def class_limits(kind: int, limits: VehicleLimits) -> VehicleLimits:
    """The continuous action's limits for an agent class: the vehicle limits for vehicles; for pedestrians
    and cyclists those within their motion envelope too (top speed 4 / 15 m/s, lateral acceleration 6 / 5
    m/s^2, its acceleration and braking), so that every motion a continuous action makes is one the motion
    vocabulary follows (the NPCs read the agent where it is)."""
    if int(kind) == AgentKind.VEHICLE:
        return limits
    env = DEFAULT_ENVELOPES[AgentKind(int(kind))]
    return replace(
        limits,
        max_speed=min(limits.max_speed, env.max_speed),
        max_lateral_accel=min(limits.max_lateral_accel, env.max_lateral_accel),
        max_accel=min(limits.max_accel, env.max_accel),
        max_brake=min(limits.max_brake, env.max_brake),
    )


def bicycle_step(
    xyh: np.ndarray,
    speed: np.ndarray,
    action: np.ndarray,
    length: np.ndarray,
    limits: VehicleLimits,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Next states ``[...,3]`` and speeds of a kinematic bicycle about the box centre (slip angle
    ``beta = atan(tan(steer) / 2)``, rear and front axles ``wheelbase / 2`` from the centre; the steering
    range shrinks with speed, see VehicleLimits; per class: :func:`class_limits`)."""
    a = np.where(action[..., 0] >= 0, action[..., 0] * limits.max_accel, action[..., 0] * limits.max_brake)
    steer = action[..., 1] * limits.steer_limit(speed, length)
    v_next = np.clip(speed + a * dt, 0.0, limits.max_speed)
    v_mean = (speed + v_next) / 2
    beta = np.arctan(np.tan(steer) / 2)
    half_base = limits.wheelbase_ratio * length / 2
    heading = xyh[..., 2]
    x = xyh[..., 0] + v_mean * np.cos(heading + beta) * dt
    y = xyh[..., 1] + v_mean * np.sin(heading + beta) * dt
    h = wrap_angle(heading + v_mean / half_base * np.sin(beta) * dt)
    return np.stack([x, y, h], -1), v_next


def delta_step(xyh: np.ndarray, action: np.ndarray) -> np.ndarray:
    """Next states ``[...,3]`` from local displacements ``(dx, dy, dh)`` (broadcasting)."""
    return to_global(xyh, np.asarray(action, dtype=np.float64))


def token_step(xyh: np.ndarray, templates: np.ndarray, token: np.ndarray | int) -> np.ndarray:
    """Next states from templates ``token`` of the agents' classes (``templates [V,3]``, or ``[n,V,3]``
    with ``xyh [n,3]`` and ``token [n]``: one table per agent)."""
    if templates.ndim == 2:
        return to_global(xyh, templates[np.asarray(token, dtype=np.int64)])
    rows = np.arange(len(templates))
    return to_global(xyh, templates[rows, np.asarray(token, dtype=np.int64)])


def action_towards(
    action_type: str,
    xyh: np.ndarray,
    speed: float,
    target: np.ndarray,
    length: float,
    limits: VehicleLimits,
    dt: float,
    templates: np.ndarray | None = None,
    agent: str = "",
) -> np.ndarray | int:
    """The action whose next state is nearest to ``target [3]`` from state ``xyh [3]`` at ``speed``
    (clipped to the action space; ``templates [V,3]`` of the agent's class for ``token``; ``limits``: the
    agent's class's, :func:`class_limits`; ``agent``: its name, for the error on a bad target)."""
    local = to_local(np.asarray(xyh, dtype=np.float64), _checked_target(target, agent))
    if action_type == "delta":
        return np.clip(local, DELTA_LOW, DELTA_HIGH).astype(np.float32)
    if action_type == "token":
        if templates is None:
            raise ValueError("action_towards: token actions need the agent's templates")
        return int(np.argmin(_corner_gap(templates, local, length)))
    # continuous: the acceleration whose step (at the mean of the two speeds, as bicycle_step moves) covers
    # the displacement ahead -- a lateral offset is the steering's to correct: counted in the speed, it
    # would speed up a car that should stop -- then the steering (searched on a grid) whose next state is
    # nearest in position and heading
    v_target = float(np.clip(2 * local[0] / dt - speed, 0.0, limits.max_speed))
    a = (v_target - speed) / dt
    a_cmd = float(np.clip(a / limits.max_accel if a >= 0 else a / limits.max_brake, -1.0, 1.0))
    steering = np.linspace(-1.0, 1.0, STEERING_CANDIDATES)
    actions = np.stack([np.full_like(steering, a_cmd), steering], -1)
    origin = np.zeros(3)
    nxt, _ = bicycle_step(origin, np.float64(speed), actions, np.float64(length), limits, dt)
    gap = ((nxt[:, :2] - local[:2]) ** 2).sum(-1) + (wrap_angle(nxt[:, 2] - local[2]) * length / 2) ** 2
    return np.array([a_cmd, steering[np.argmin(gap)]], dtype=np.float32)


def _checked_target(target: object, agent: str = "") -> np.ndarray:
    """``target`` as a float64 ``(x, y, heading)`` array; a ValueError naming ``agent`` for anything else."""
    try:
        state = np.asarray(target, dtype=np.float64)
    except (TypeError, ValueError):
        state = None
    if state is None or state.shape != (3,) or not np.isfinite(state).all():
        shape = f" (shape {np.shape(target)})" if state is not None else ""
        raise ValueError(
            f"action_towards: agent {agent!r}: expected a target state as a finite (x, y, heading) "
            f"array of shape (3,), got {str(target)[:200]}{shape}"
        )
    return state


def _corner_gap(templates: np.ndarray, local: np.ndarray, length: float) -> np.ndarray:
    """Squared distance between templates and a local displacement, heading error weighted by the
    distance of the box's front from its centre (a cheap stand-in for the tokenizer's corner distance)."""
    d = templates - local
    d[:, 2] = wrap_angle(d[:, 2]) * (length / 2)
    return (d**2).sum(-1)
