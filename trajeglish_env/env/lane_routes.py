"""Routes past the end of the log: an external agent's logged path continued along the lane centres of
the map (the next lane is the one starting near the current end, heading the same way), so episodes
longer than the log keep a route to follow, observe and be rewarded on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.env.routes import Paths, logged_paths
from trajeglish_env.geometry import wrap_angle
from trajeglish_env.scenario import LANE_KINDS, Scenario

SNAP = 3.0  # m: a lane continues the route if one of its points is this close to the route's end
MAX_TURN = np.pi / 4  # rad: ... and its direction there is within this of the route's heading
MAX_HOPS = 256  # lanes chained at most (a looping track is followed round and round)


@dataclass(frozen=True)
class LanePoints:
    """Every lane-centre point of a scene with its lane, its index along the lane and its direction."""

    xy: np.ndarray  # [K,2]
    lane: np.ndarray  # [K]
    heading: np.ndarray  # [K] direction of the lane at the point
    last: np.ndarray  # [K] the lane's last point (nothing follows it)
    lanes: list[np.ndarray]

    @classmethod
    def of(cls, scenario: Scenario) -> LanePoints:
        lanes = [p for p in scenario.polylines(LANE_KINDS) if len(p) >= 2]
        if not lanes:
            empty = np.zeros(0)
            return cls(np.zeros((0, 2)), empty.astype(np.int64), empty, empty.astype(bool), [])
        heading = []
        for p in lanes:
            d = np.diff(p, axis=0)
            h = np.arctan2(d[:, 1], d[:, 0])
            heading.append(np.concatenate([h, h[-1:]]))
        return cls(
            np.concatenate(lanes),
            np.concatenate([np.full(len(p), i) for i, p in enumerate(lanes)]),
            np.concatenate(heading),
            np.concatenate([np.arange(len(p)) == len(p) - 1 for p in lanes]),
            lanes,
        )


def lane_continuation(lanes: LanePoints, start: np.ndarray, heading: float, length: float) -> np.ndarray:
    """Points ``[M,2]`` continuing a route from ``start`` (heading ``heading``) along the lanes for about
    ``length`` m: at each hop, the lane point nearest the end that points the same way and is not behind
    it, then the rest of that lane. Empty when no lane continues the route."""
    out: list[np.ndarray] = []
    p, h, total = np.asarray(start, dtype=np.float64), float(heading), 0.0
    for _ in range(MAX_HOPS):
        if total >= length or not len(lanes.xy):
            break
        rel = lanes.xy - p
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ahead = rel @ np.array([np.cos(h), np.sin(h)]) >= -0.5
        ok = (dist <= SNAP) & (np.abs(wrap_angle(lanes.heading - h)) <= MAX_TURN) & ahead & ~lanes.last
        if not ok.any():
            break
        k = int(np.flatnonzero(ok)[np.argmin(dist[ok])])
        lane = lanes.lanes[lanes.lane[k]]
        first = k - int(np.flatnonzero(lanes.lane == lanes.lane[k])[0])
        rest = lane[first + 1 :]
        if len(rest) < 1:
            break
        piece = np.concatenate([p[None], rest])
        step = np.hypot(*np.diff(piece, axis=0).T).sum()
        if step < 0.5:  # nothing gained: a degenerate lane end
            break
        out.append(rest)
        total += step
        p = rest[-1]
        d = rest[-1] - (rest[-2] if len(rest) > 1 else piece[-2])
        h = float(np.arctan2(d[1], d[0]))
    return np.concatenate(out) if out else np.zeros((0, 2))


def extended_routes(scenario: Scenario, agents: np.ndarray, extra: float, spacing: float = 1.0) -> Paths:
    """The logged paths of ``agents`` from the current step on, each continued along the lanes by about
    ``extra`` m past its end (as far as the lanes go)."""
    cur = scenario.current_index
    xyh, valid = scenario.xyh[agents, cur:], scenario.valid[agents, cur:]
    lanes = LanePoints.of(scenario)
    tracks = []  # per agent: its logged states, then the continuation's points with their directions
    for a in range(len(agents)):
        steps = np.flatnonzero(valid[a])
        logged = xyh[a, steps]
        more = (
            lane_continuation(lanes, logged[-1, :2], logged[-1, 2], extra) if len(steps) else np.zeros((0, 2))
        )
        if len(more):
            d = np.diff(np.concatenate([logged[-1:, :2], more]), axis=0)
            more = np.concatenate([more, np.arctan2(d[:, 1], d[:, 0])[:, None]], axis=1)
        tracks.append(np.concatenate([logged, more.reshape(-1, 3)]))
    longest = max((len(t) for t in tracks), default=1)
    path_xyh = np.zeros((len(agents), longest, 3))
    path_valid = np.zeros((len(agents), longest), dtype=bool)
    for a, t in enumerate(tracks):
        path_xyh[a, : len(t)] = t
        path_valid[a, : len(t)] = True
    return logged_paths(path_xyh, path_valid, spacing=spacing)
