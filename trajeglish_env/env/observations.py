"""Observations of an external agent, taken at its turn in the step (so they show the moves of every
agent that acted before it). Fixed size, finite bounds, everything in the agent's frame (x forward, y left).

``vector`` (float32, every entry in [-1, 1]; R = ``radius`` m, K neighbours, M map points, Q route points):

| slice | features (scale) |
|---|---|
| ego [0:8] | speed (/30 m/s), longitudinal acceleration (/10 m/s^2), yaw rate (/1 rad/s), length (/10 m), |
| | width (/5 m), fraction of the route done, lateral offset from the route (/5 m, left +), |
| | heading error to the route (/pi) |
| neighbours [8 : 8+10K] | per agent, nearest first: present, x, y (/R), cos and sin of the relative |
| | heading, vx, vy (/30 m/s), length (/10), width (/5), moved-this-step flag |
| map [.. : ..+6M] | per point, nearest first (ties: in the scene's point order; polylines resampled |
| | every ``map_spacing`` m): present, x, y (/R), is lane centre, is road line, is road edge |
| route [.. : ..+2Q] | the logged route ``route_spacing``, 2 x ``route_spacing``, ... m ahead of the agent's |
| | progress: x, y (/R) |
| signals [.. : ..+6S] | only with ``signals`` S > 0: per stop point of a signal-controlled lane, nearest |
| | first: present, x, y (/R), red, yellow, green (:mod:`~trajeglish_env.env.signal_features`) |

Neighbours show each agent's latest decided state: its next state if it already moved this step (the
flag is 1), else its current one. ``bev`` (uint8, C x H x W, ``bev_size`` pixels of ``bev_resolution`` m,
the agent at the centre heading up): channel 0 lane centres, 1 road edges (255) and road lines (128),
2 agents that have not moved yet this step, 3 agents that have, 4 the agent itself and its route.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gymnasium import spaces

from trajeglish_env.batch_geometry import EDGE, LANE, LINE, OTHER
from trajeglish_env.env.batch_outcomes import Pictures
from trajeglish_env.env.config import ObservationConfig
from trajeglish_env.env.signal_features import SIGNAL_FEATURES
from trajeglish_env.geometry import transform_points
from trajeglish_env.scenario import LANE_KINDS, ROAD_EDGE_KINDS, ROAD_LINE_KINDS, Scenario

EGO_FEATURES = 8
NEIGHBOUR_FEATURES = 10
MAP_FEATURES = 6
BEV_CHANNELS = 5


@dataclass(frozen=True)
class EgoState:
    """What the observation needs about the observing agent besides the scene picture."""

    agent: int
    speed: float
    accel: float
    yaw_rate: float
    route_fraction: float
    lateral: float
    heading_error: float
    route_ahead: np.ndarray  # [Q,2] global points of the route ahead


def sample_map_points(scenario: Scenario, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Map points about ``spacing`` m apart along every polyline (``[Q,2]``) and their category ``[Q]``
    (0 lane centre, 1 road line, 2 road edge, 3 other), vectorized over the ragged polylines."""
    pts, off = scenario.map_points, scenario.map_offsets
    if len(pts) == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int8)
    poly = np.repeat(np.arange(len(off) - 1), np.diff(off))
    step = np.zeros(len(pts))
    step[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    starts = off[:-1][np.diff(off) > 0]
    step[starts] = 0.0
    cum = np.cumsum(step)
    arc = cum - cum[off[:-1]][poly]
    bucket = np.floor(arc / spacing).astype(np.int64)
    keep = np.ones(len(pts), dtype=bool)
    keep[1:] = (bucket[1:] != bucket[:-1]) | (poly[1:] != poly[:-1])
    category = np.full(len(off) - 1, OTHER, dtype=np.int8)
    kinds = scenario.map_kind.astype(np.int64)
    category[np.isin(kinds, list(LANE_KINDS))] = LANE
    category[np.isin(kinds, list(ROAD_LINE_KINDS))] = LINE
    category[np.isin(kinds, list(ROAD_EDGE_KINDS))] = EDGE
    return pts[keep], category[poly[keep]]


class VectorObserver:
    """The ``vector`` observation (layout in the module docstring): this scene's map points and the space;
    the observations themselves are computed for many agents and scenes at once by
    :func:`~trajeglish_env.batch_geometry.vector_observations`."""

    def __init__(self, scenario: Scenario, config: ObservationConfig):
        self.sc, self.cfg = scenario, config
        self.points, self.category = sample_map_points(scenario, config.map_spacing)
        self.space = observation_space("vector", config)  # one definition of the layout's size
        self.size = int(self.space.shape[0])


class BevObserver:
    """The ``bev`` observation: a uint8 raster ``[5, S, S]`` centred on the agent, heading up."""

    def __init__(self, scenario: Scenario, config: ObservationConfig):
        self.sc, self.cfg = scenario, config
        self.points, self.category = sample_map_points(scenario, config.bev_resolution / 2)
        n = config.bev_size
        self.space = spaces.Box(0, 255, shape=(BEV_CHANNELS, n, n), dtype=np.uint8)
        longest = float(scenario.size.max()) if scenario.num_agents else 1.0
        k = int(np.ceil(longest / (config.bev_resolution / 2))) + 1
        u = np.linspace(-0.5, 0.5, k)
        self._box_grid = np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)  # unit box samples

    def _pixels(self, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, r = self.cfg.bev_size, self.cfg.bev_resolution
        row = np.floor(n / 2 - local[..., 0] / r).astype(np.int64)
        col = np.floor(n / 2 - local[..., 1] / r).astype(np.int64)
        inside = (row >= 0) & (row < n) & (col >= 0) & (col < n)
        return row[inside], col[inside], inside

    def _boxes(self, origin: np.ndarray, state: np.ndarray, size: np.ndarray) -> np.ndarray:
        """Local sample points ``[k*G, 2]`` covering the boxes ``state [k,3]`` of ``size [k,2]``."""
        body = self._box_grid[None] * size[:, None, :]  # [k,G,2] in each box's frame
        c, s = np.cos(state[:, 2])[:, None], np.sin(state[:, 2])[:, None]
        x = state[:, None, 0] + c * body[..., 0] - s * body[..., 1]
        y = state[:, None, 1] + s * body[..., 0] + c * body[..., 1]
        return transform_points(np.stack([x, y], -1).reshape(-1, 2), origin)

    def observe(self, ego: EgoState, pictures: Pictures, scene: int) -> np.ndarray:
        """The raster of ``ego`` in scene ``scene`` of ``pictures`` (the scene as it stands now)."""
        k = self.sc.num_agents
        state, present = pictures.state[scene, :k], pictures.present[scene, :k]
        moved = pictures.moved[scene, :k]
        n = self.cfg.bev_size
        out = np.zeros((BEV_CHANNELS, n, n), dtype=np.uint8)
        origin = state[ego.agent]
        if len(self.points):
            rr, cc, inside = self._pixels(transform_points(self.points, origin))
            cat = self.category[inside]
            lane = cat == LANE
            out[0, rr[lane], cc[lane]] = 255
            line = cat == LINE
            out[1, rr[line], cc[line]] = 128
            edge = cat == EDGE
            out[1, rr[edge], cc[edge]] = 255
        others = np.flatnonzero(present & (np.arange(k) != ego.agent))
        for channel, mask in ((2, ~moved[others]), (3, moved[others])):
            agents = others[mask]
            if len(agents):
                rr, cc, _ = self._pixels(self._boxes(origin, state[agents], self.sc.size[agents]))
                out[channel, rr, cc] = 255
        rr, cc, _ = self._pixels(self._boxes(origin, origin[None], self.sc.size[ego.agent][None]))
        out[4, rr, cc] = 255
        rr, cc, _ = self._pixels(transform_points(ego.route_ahead, origin))
        out[4, rr, cc] = 128
        return out


def make_observer(kind: str, scenario: Scenario, config: ObservationConfig) -> VectorObserver | BevObserver:
    """The observer of an observation type for one scene."""
    if kind == "vector":
        return VectorObserver(scenario, config)
    if kind == "bev":
        return BevObserver(scenario, config)
    raise ValueError(f"unknown observation type {kind!r}")


def observation_space(kind: str, config: ObservationConfig) -> spaces.Box:
    """The observation space of a type (independent of the scene)."""
    if kind == "vector":
        size = EGO_FEATURES + NEIGHBOUR_FEATURES * config.neighbours + MAP_FEATURES * config.map_points
        size += 2 * config.route_points + SIGNAL_FEATURES * config.signals
        return spaces.Box(-1.0, 1.0, shape=(size,), dtype=np.float32)
    if kind == "bev":
        n = config.bev_size
        return spaces.Box(0, 255, shape=(BEV_CHANNELS, n, n), dtype=np.uint8)
    raise ValueError(f"unknown observation type {kind!r}")
