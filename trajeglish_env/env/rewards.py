"""Per-step outcome of the external agents: collisions (box overlap with any other agent), off-road (a box
corner beyond a road edge), progress along the logged route, comfort, and the reward of
:class:`~trajeglish_env.env.config.RewardConfig` (vectorized over agents)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.batch_geometry import collision_flags
from trajeglish_env.env.config import RewardConfig
from trajeglish_env.geometry import box_corners
from trajeglish_env.metrics.road_edges import RoadEdges, signed_distance_to_road_edges
from trajeglish_env.scenario import AgentKind


@dataclass(frozen=True)
class StepOutcome:
    """Arrays over the evaluated external agents: reward, collision, offroad, goal reached, progress gained
    (m), comfort penalty (in units of ``comfort_accel``)."""

    reward: np.ndarray
    collision: np.ndarray
    offroad: np.ndarray
    goal: np.ndarray
    progress: np.ndarray
    discomfort: np.ndarray


def collisions(xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, agents: np.ndarray) -> np.ndarray:
    """``[k]`` True where agent ``agents[i]`` overlaps any other valid agent (states ``xyh [N,3]``)."""
    agents = np.asarray(agents, dtype=np.int64)
    return collision_flags(xyh[None], valid[None], size[None], np.zeros(len(agents), np.int64), agents)


def offroad(
    xyh: np.ndarray, size: np.ndarray, kind: np.ndarray, edges: RoadEdges | None, margin: float
) -> np.ndarray:
    """``[k]`` True where a vehicle's box has a corner more than ``margin`` m beyond a road edge
    (pedestrians and cyclists are never off-road)."""
    out = np.zeros(len(xyh), dtype=bool)
    vehicles = np.flatnonzero(kind == AgentKind.VEHICLE)
    if edges is None or len(vehicles) == 0:
        return out
    corners = box_corners(xyh[vehicles], size[vehicles])
    out[vehicles] = signed_distance_to_road_edges(corners, edges).max(axis=-1) > margin
    return out


def step_reward(
    config: RewardConfig,
    progress: np.ndarray,
    route_length: np.ndarray,
    collision: np.ndarray,
    off: np.ndarray,
    goal: np.ndarray,
    accel_long: np.ndarray,
    accel_lat: np.ndarray,
) -> StepOutcome:
    """Combine the terms of one step into rewards (see RewardConfig)."""
    excess = np.maximum(np.abs(accel_long) - config.comfort_accel, 0.0) + np.maximum(
        np.abs(accel_lat) - config.comfort_accel, 0.0
    )
    discomfort = np.minimum(excess / config.comfort_accel, config.comfort_cap)
    reward = (
        config.progress * progress / np.maximum(route_length, 10.0)
        + config.collision * collision
        + config.offroad * off
        + config.comfort * discomfort
        + config.goal * goal
    )
    return StepOutcome(reward, collision, off, goal, progress, discomfort)
