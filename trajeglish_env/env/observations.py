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
| map [.. : ..+6M] | per point, nearest first (polylines resampled every ``map_spacing`` m): present, |
| | x, y (/R), is lane centre, is road line, is road edge |
| route [.. : ..+2Q] | the logged route ``route_spacing``, 2 x ``route_spacing``, ... m ahead of the agent's |
| | progress: x, y (/R) |

Neighbours show each agent's latest decided state: its next state if it already moved this step (the
flag is 1), else its current one. ``bev`` (uint8, C x H x W, ``bev_size`` pixels of ``bev_resolution`` m,
the agent at the centre heading up): channel 0 lane centres, 1 road edges (255) and road lines (128),
2 agents that have not moved yet this step, 3 agents that have, 4 the agent itself and its route.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gymnasium import spaces

from trajeglish_env.env.config import ObservationConfig
from trajeglish_env.geometry import to_local, transform_points
from trajeglish_env.scenario import LANE_KINDS, ROAD_EDGE_KINDS, ROAD_LINE_KINDS, Scenario

EGO_FEATURES = 8
NEIGHBOUR_FEATURES = 10
MAP_FEATURES = 6
BEV_CHANNELS = 5
LANE, LINE, EDGE, OTHER = 0, 1, 2, 3


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


@dataclass(frozen=True)
class Picture:
    """Every agent's latest decided state ``[N,3]``, presence, velocity ``[N,2]`` and moved flag."""

    state: np.ndarray
    present: np.ndarray
    velocity: np.ndarray
    moved: np.ndarray


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
    """The ``vector`` observation (layout in the module docstring)."""

    def __init__(self, scenario: Scenario, config: ObservationConfig):
        self.sc, self.cfg = scenario, config
        self.points, self.category = sample_map_points(scenario, config.map_spacing)
        size = EGO_FEATURES + NEIGHBOUR_FEATURES * config.neighbours + MAP_FEATURES * config.map_points
        self.size = size + 2 * config.route_points
        self.space = spaces.Box(-1.0, 1.0, shape=(self.size,), dtype=np.float32)

    def observe(self, ego: EgoState, pic: Picture) -> np.ndarray:
        cfg, sc, radius = self.cfg, self.sc, self.cfg.radius
        origin = pic.state[ego.agent]
        head = [
            ego.speed / 30.0,
            ego.accel / 10.0,
            ego.yaw_rate,
            sc.size[ego.agent, 0] / 10.0,
            sc.size[ego.agent, 1] / 5.0,
            ego.route_fraction,
            ego.lateral / 5.0,
            ego.heading_error / np.pi,
        ]
        # neighbours: nearest present agents within the radius
        rel = to_local(origin, pic.state)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        cand = np.flatnonzero(pic.present & (dist <= radius) & (np.arange(sc.num_agents) != ego.agent))
        near = cand[np.argsort(dist[cand], kind="stable")[: cfg.neighbours]]
        c, s = np.cos(origin[2]), np.sin(origin[2])
        v = pic.velocity[near]
        feats = np.stack(
            [
                np.ones(len(near)),
                rel[near, 0] / radius,
                rel[near, 1] / radius,
                np.cos(rel[near, 2]),
                np.sin(rel[near, 2]),
                (c * v[:, 0] + s * v[:, 1]) / 30.0,
                (-s * v[:, 0] + c * v[:, 1]) / 30.0,
                sc.size[near, 0] / 10.0,
                sc.size[near, 1] / 5.0,
                pic.moved[near].astype(np.float64),
            ],
            axis=-1,
        )
        neighbours = np.zeros((cfg.neighbours, NEIGHBOUR_FEATURES))
        neighbours[: len(near)] = feats
        # map points: nearest within the radius
        mp = np.zeros((cfg.map_points, MAP_FEATURES))
        if len(self.points):
            local = transform_points(self.points, origin)
            d2 = (local**2).sum(-1)
            inside = np.flatnonzero(d2 <= radius * radius)
            if len(inside) > cfg.map_points:
                inside = inside[np.argpartition(d2[inside], cfg.map_points - 1)[: cfg.map_points]]
            inside = inside[np.argsort(d2[inside], kind="stable")]
            cat = self.category[inside]
            m = len(inside)
            mp[:m, 0] = 1.0
            mp[:m, 1:3] = local[inside] / radius
            mp[:m, 3] = cat == LANE
            mp[:m, 4] = cat == LINE
            mp[:m, 5] = cat == EDGE
        route = transform_points(ego.route_ahead, origin) / radius
        out = np.concatenate([np.asarray(head), neighbours.ravel(), mp.ravel(), route.ravel()])
        return np.clip(out, -1.0, 1.0).astype(np.float32)


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

    def observe(self, ego: EgoState, pic: Picture) -> np.ndarray:
        n = self.cfg.bev_size
        out = np.zeros((BEV_CHANNELS, n, n), dtype=np.uint8)
        origin = pic.state[ego.agent]
        if len(self.points):
            rr, cc, inside = self._pixels(transform_points(self.points, origin))
            cat = self.category[inside]
            lane = cat == LANE
            out[0, rr[lane], cc[lane]] = 255
            line = cat == LINE
            out[1, rr[line], cc[line]] = 128
            edge = cat == EDGE
            out[1, rr[edge], cc[edge]] = 255
        others = np.flatnonzero(pic.present & (np.arange(self.sc.num_agents) != ego.agent))
        for channel, mask in ((2, ~pic.moved[others]), (3, pic.moved[others])):
            agents = others[mask]
            if len(agents):
                rr, cc, _ = self._pixels(self._boxes(origin, pic.state[agents], self.sc.size[agents]))
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
        return spaces.Box(-1.0, 1.0, shape=(size + 2 * config.route_points,), dtype=np.float32)
    if kind == "bev":
        n = config.bev_size
        return spaces.Box(0, 255, shape=(BEV_CHANNELS, n, n), dtype=np.uint8)
    raise ValueError(f"unknown observation type {kind!r}")
