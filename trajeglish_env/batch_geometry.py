"""The per-step geometry of many scenes in one NumPy pass: collisions, off-road, the pictures the
observations show, and the ``vector`` observation itself, for the external agents of B scenes.

Scene by scene, these cost a few dozen small NumPy calls each, which dominated a batched env's stepping
time besides the model. Here the scenes' arrays are padded to common shapes and every formula runs once
for all of them. Each number is computed elementwise or along its own scene's row, and padding never wins
a minimum or a sort, so a scene gets the same results alone (the unbatched env calls these functions with
one scene) as in any batch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from trajeglish_env.geometry import box_corners, to_local
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.metrics.road_edges import Z_STRETCH, RoadEdges
from trajeglish_env.scenario import ROAD_EDGE_KINDS, AgentKind, Scenario

LANE, LINE, EDGE, OTHER = 0, 1, 2, 3  # categories of the observation's map points


def pad_stack(arrays: Sequence[np.ndarray], fill: float | bool = 0, last: bool = False) -> np.ndarray:
    """``[len(arrays), ...]``: arrays ragged along their first axis (``last``: their last axis), stacked
    and padded with ``fill``."""
    longest = max(a.shape[-1 if last else 0] for a in arrays)
    shape = (*arrays[0].shape[:-1], longest) if last else (longest, *arrays[0].shape[1:])
    out = np.full((len(arrays), *shape), fill, dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[(i, ..., slice(0, a.shape[-1])) if last else (i, slice(0, len(a)))] = a
    return out


def road_edges(scenario: Scenario) -> RoadEdges | None:
    """The scene's road edges (None when its map has none: off-road is then never reported)."""
    lines = [p for p in scenario.polylines(ROAD_EDGE_KINDS) if len(p) >= 2]
    return RoadEdges.from_polylines(lines) if lines else None


class PaddedRows:
    """One per-row array of a batch, ragged along the first axis of its rows (``last``: the last axis) and
    kept padded with ``fill``: a row is rewritten only when its source object changes (a scene reset), and
    the padding grows when needed."""

    def __init__(self, fill: float | bool = 0, last: bool = False):
        self.fill, self.last = fill, last
        self.data: np.ndarray | None = None
        self.sources: list[object] = []

    def sync(self, sources: Sequence[object], get: Callable[[object], np.ndarray]) -> np.ndarray:
        """The padded array of ``sources``: row i is ``get(sources[i])``, computed only for the rows whose
        source is not the one of the previous call."""
        if self.data is None or len(sources) != len(self.sources):
            self.data = pad_stack([get(s) for s in sources], self.fill, self.last)
        else:
            fresh = {i: get(s) for i, s in enumerate(sources) if self.sources[i] is not s}
            if fresh:
                longest = max(v.shape[-1 if self.last else 0] for v in fresh.values())
                width = self.data.shape[-1 if self.last else 1]
                if longest > width:
                    shape = list(self.data.shape)
                    shape[-1 if self.last else 1] = longest
                    bigger = np.full(shape, self.fill, self.data.dtype)
                    bigger[(..., slice(0, width)) if self.last else (slice(None), slice(0, width))] = (
                        self.data
                    )
                    self.data = bigger
                for i, v in fresh.items():
                    self.data[i] = self.fill
                    self.data[(i, ..., slice(0, v.shape[-1])) if self.last else (i, slice(0, len(v)))] = v
        self.sources = list(sources)
        return self.data


# ---------------------------------------------------------------------------------------------- collisions
def collision_flags(
    xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, scene: np.ndarray, agent: np.ndarray
) -> np.ndarray:
    """``[Q]`` True where agent ``agent[q]`` of scene ``scene[q]`` overlaps any other valid agent of its
    scene (states ``xyh [B,N,3]``, ``valid [B,N]``, ``size [B,N,2]``; padding agents are not valid)."""
    hit = box_collisions(xyh[scene, agent][:, None], size[scene, agent][:, None], xyh[scene], size[scene])
    hit &= valid[scene] & (np.arange(xyh.shape[1])[None] != agent[:, None])
    return hit.any(axis=1) & valid[scene, agent]


# ------------------------------------------------------------------------------------------------ off-road
def edge_rows(edges: RoadEdges | None) -> tuple[np.ndarray, np.ndarray]:
    """The road-edge segments as ``[7, S]`` float32 :attr:`RoadEdges.columns` (start x, y, z, direction x,
    y, z, inverse squared 2-D length) and ``[3, S]`` int64 links (previous and following segment or -1,
    and 1 where the segment starts at a convex vertex); ``S`` = 0 without edges."""
    if edges is None:
        return np.zeros((7, 0), np.float32), np.zeros((3, 0), np.int64)
    links = np.stack([edges.previous, edges.following, edges.convex_start]).astype(np.int64)
    return edges.columns, links


def _rows(a: np.ndarray, scene: np.ndarray) -> np.ndarray:
    """``a[scene]``, without a copy when ``scene`` is every row in order (one query per scene)."""
    if len(scene) == len(a) and (scene == np.arange(len(a))).all():
        return a
    return a[scene]


def selection_d2(cols: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Squared 3-D distances (z stretched, queries at z = 0: exactly the planar value on flat maps) from
    points ``x, y [Q,C]`` to segments ``cols [Q,7,K]`` -> ``[Q,C,K]`` (float32, the reference's formula)."""
    f32 = np.float32
    cols = cols[:, :, None, :]
    ax, ay, az, dx, dy, dz, inverse = (cols[:, k] for k in range(7))
    ux, uy = x[..., None] - ax, y[..., None] - ay
    t = ux * dx
    t += uy * dy
    t *= inverse
    np.clip(t, 0, 1, out=t)
    ux -= t * dx  # rx, ry: in place (the same numbers, fewer temporaries on this hot path)
    uy -= t * dy
    if not (az.any() or dz.any()):  # a flat map: the z term is +0, which changes no number
        ux *= ux
        uy *= uy
        ux += uy
        return ux
    rz = Z_STRETCH * (f32(0) - az - t * dz)
    return ux * ux + uy * uy + rz * rz


def nearest_segments(
    columns: np.ndarray, count: np.ndarray, scene: np.ndarray, points: np.ndarray
) -> np.ndarray:
    """Index ``[Q,C]`` of the road-edge segment nearest (as the reference chooses it: 3-D, z stretched,
    first on ties) to each of ``points [Q,C,2]`` among every segment of its scene ``scene [Q]``."""
    pts = points.astype(np.float32)
    d2 = selection_d2(_rows(columns, scene), pts[..., 0], pts[..., 1])
    real = np.arange(columns.shape[2])[None, None] < count[scene][:, None, None]
    return np.argmin(np.where(real, d2, np.inf), axis=-1)


def signed_distances_to(
    columns: np.ndarray, links: np.ndarray, scene: np.ndarray, points: np.ndarray, nearest: np.ndarray
) -> np.ndarray:
    """Signed distances ``[Q,C]`` (float32) from ``points [Q,C,2]`` to their ``nearest`` segments, the sign
    beyond a segment's end taken from the vertex it shares with its neighbour (see ``road_edges``)."""
    f32 = np.float32
    pts = points.astype(f32)
    x, y = pts[..., 0], pts[..., 1]
    own = scene[:, None]
    sx, sy, sdx, sdy = (columns[own, k, nearest] for k in (0, 1, 3, 4))
    ux, uy = x - sx, y - sy
    length2 = sdx * sdx + sdy * sdy
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = np.where(length2 > 0, (ux * sdx + uy * sdy) / length2, f32(0))
    tc = np.clip(tt, 0, 1)
    rx, ry = ux - tc * sdx, uy - tc * sdy
    magnitude = np.sqrt(rx * rx + ry * ry)
    sign = np.sign(ux * sdy - uy * sdx)  # -1 left (road), +1 right
    previous, following = links[own, 0, nearest], links[own, 1, nearest]
    before = (tt < 0) & (previous >= 0)
    beyond = before | ((tt > 1) & (following >= 0))
    if beyond.any():
        qq, cc = np.nonzero(beyond)
        sc = scene[qq]
        first = before[qq, cc]
        other = np.where(first, previous[qq, cc], following[qq, cc])
        convex = np.where(first, links[sc, 2, nearest[qq, cc]], links[sc, 2, other]) > 0
        ox, oy = x[qq, cc] - columns[sc, 0, other], y[qq, cc] - columns[sc, 1, other]
        other_side = np.sign(ox * columns[sc, 4, other] - oy * columns[sc, 3, other])
        own_side = sign[qq, cc]
        sign[qq, cc] = np.where(convex, np.maximum(own_side, other_side), np.minimum(own_side, other_side))
    return sign * magnitude


def road_edge_distances(
    columns: np.ndarray, links: np.ndarray, count: np.ndarray, scene: np.ndarray, points: np.ndarray
) -> np.ndarray:
    """Signed distances ``[Q, C]`` (float32) from 2-D ``points [Q, C, 2]`` to the road edges of their scenes
    ``scene [Q]`` (``columns [B, 7, S]``, ``links [B, 3, S]``: :func:`edge_rows` of each scene, padded;
    ``count [B]`` real segments, > 0 for every queried scene): the rule of
    :func:`~trajeglish_env.metrics.road_edges.signed_distance_to_road_edges`, number for number."""
    return signed_distances_to(columns, links, scene, points, nearest_segments(columns, count, scene, points))


def nearest_segments_near(
    columns: np.ndarray,
    count: np.ndarray,
    scene: np.ndarray,
    points: np.ndarray,
    candidates: np.ndarray,
    anchor: np.ndarray,
    reach: float | np.ndarray,
) -> np.ndarray:
    """:func:`nearest_segments`, scanning per query only ``candidates [Q,K]`` (-1 padding): the segments
    within ``reach`` m (2-D; a number, or ``[Q,1]`` per query) of ``anchor [Q,2]``. A segment left out is
    farther than ``reach`` minus the point's distance to the anchor, in 2-D and so in 3-D; when the best
    candidate is nearer than that (1 m to spare for float32 rounding) it is the reference's choice, ties
    included (candidates ascend), else the point's query is answered by a full scan."""
    pts = points.astype(np.float32)
    safe = np.maximum(candidates, 0)
    cols = columns[scene[:, None, None], np.arange(7)[None, :, None], safe[:, None, :]]  # [Q,7,K]
    d2 = np.where((candidates >= 0)[:, None, :], selection_d2(cols, pts[..., 0], pts[..., 1]), np.inf)
    best = np.argmin(d2, axis=-1)  # [Q,C]
    nearest = np.take_along_axis(candidates, best, 1)
    margin = reach - np.hypot(points[..., 0] - anchor[:, None, 0], points[..., 1] - anchor[:, None, 1]) - 1.0
    sure = (margin > 0) & (np.take_along_axis(d2, best[..., None], -1)[..., 0] <= margin * margin)
    unsure = np.flatnonzero(~sure.all(axis=1))
    if len(unsure):
        nearest[unsure] = nearest_segments(columns, count, scene[unsure], points[unsure])
    return nearest


class NearbyItems:
    """Per query row of a batch (a scene's agent), the items of its scene (map points, road-edge segments)
    within ``reach`` m of an anchor, re-chosen when the agent is more than ``drift`` m from its anchor or
    the row's key changes: a query near the anchor scans only them (callers say why that is exact)."""

    def __init__(self, reach: float, drift: float):
        if not reach > drift > 0:
            raise ValueError(f"NearbyItems: need reach > drift > 0, got reach={reach}, drift={drift}")
        self.reach, self.drift = float(reach), float(drift)
        self.keys: list[tuple[object, int]] = []
        self.anchor = np.zeros((0, 2))
        self.lists: list[np.ndarray] = []
        self.index = np.zeros((0, 0), np.int64)
        self.version = 0

    def update(
        self,
        keys: Sequence[tuple[object, int]],
        centres: np.ndarray,
        distances: Callable[[object, np.ndarray], np.ndarray],
    ) -> np.ndarray:
        """Candidates ``[Q,K]`` (ascending, -1 padding) of rows keyed ``(scene object, agent)`` whose agents
        are at ``centres [Q,2]``; ``distances(scene, point)`` gives every item's distance to a point."""
        q = len(keys)
        if len(self.keys) != q:
            self.keys, self.anchor = [(None, -1)] * q, np.full((q, 2), np.inf)
            self.lists = [np.zeros(0, np.int64)] * q
        away = ~(np.hypot(centres[:, 0] - self.anchor[:, 0], centres[:, 1] - self.anchor[:, 1]) <= self.drift)
        stale = [
            i for i, k in enumerate(keys) if away[i] or self.keys[i][0] is not k[0] or self.keys[i][1] != k[1]
        ]
        for i in stale:
            self.lists[i] = np.flatnonzero(distances(keys[i][0], centres[i]) <= self.reach)
            self.anchor[i], self.keys[i] = centres[i], keys[i]
        if stale or self.index.shape[0] != q:
            self.index = pad_stack(self.lists, -1) if q else np.zeros((0, 0), np.int64)
            self.version += 1
        return self.index


def point_segment_distances(columns: np.ndarray, point: np.ndarray) -> np.ndarray:
    """2-D distances (float64) from ``point [2]`` to the segments ``columns [7,S]`` of :func:`edge_rows`."""
    ax, ay, dx, dy = (columns[k].astype(np.float64) for k in (0, 1, 3, 4))
    ux, uy = point[0] - ax, point[1] - ay
    length2 = dx * dx + dy * dy
    t = np.clip(
        np.where(length2 > 0, (ux * dx + uy * dy) / np.where(length2 > 0, length2, 1.0), 0.0), 0.0, 1.0
    )
    return np.hypot(ux - t * dx, uy - t * dy)


def offroad_flags(
    xyh: np.ndarray,
    size: np.ndarray,
    kind: np.ndarray,
    columns: np.ndarray,
    links: np.ndarray,
    count: np.ndarray,
    scene: np.ndarray,
    margin: np.ndarray,
    nearby: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> np.ndarray:
    """``[Q]`` True where a vehicle's box (``xyh [Q,3]``, ``size [Q,2]``, ``kind [Q]``) has a corner more
    than ``margin [Q]`` m beyond a road edge of its scene ``scene [Q]`` (scenes without edges: never).
    ``nearby = (candidates [Q,K], anchor [Q,2], reach)`` restricts the scan (see
    :func:`nearest_segments_near`; the same answer)."""
    out = np.zeros(len(xyh), dtype=bool)
    check = np.flatnonzero((kind == AgentKind.VEHICLE) & (count[scene] > 0))
    if len(check):
        corners = box_corners(xyh[check], size[check])
        rows = scene[check]
        if nearby is None:
            nearest = nearest_segments(columns, count, rows, corners)
        else:
            candidates, anchor, reach = nearby
            nearest = nearest_segments_near(
                columns, count, rows, corners, candidates[check], anchor[check], reach
            )
        distance = signed_distances_to(columns, links, rows, corners, nearest)
        out[check] = distance.max(axis=-1) > margin[check]
    return out


# ------------------------------------------------------------------------------------------------ pictures
def latest_states(
    now: np.ndarray,
    after: np.ndarray,
    before: np.ndarray,
    valid_now: np.ndarray,
    valid_after: np.ndarray,
    valid_before: np.ndarray,
    moved: np.ndarray,
    dt: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each agent's latest decided state ``[...,3]`` (the next one if it moved this step), presence and
    velocity ``[...,2]`` (m/s over the step that led there), from its states at ``t`` (``now``), ``t + 1``
    (``after``, ``valid_after`` False past the end) and ``t - 1`` (``before``, ``valid_before`` False at
    the first step); ``dt`` broadcasts against ``[...]``."""
    nxt = moved & valid_after
    cur = valid_now & ~moved
    state = np.where(nxt[..., None], after, now)
    prev = np.where(nxt[..., None], now, before)
    prev_ok = np.where(nxt, valid_now, valid_before)
    present = nxt | cur
    velocity = np.where((present & prev_ok)[..., None], (state[..., :2] - prev[..., :2]) / dt[..., None], 0.0)
    return state, present, velocity


# ------------------------------------------------------------------------------------------- observations
def nearest_first(key: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``key [Q, M]`` (``inf``: not a candidate), the indices ``[Q, k]`` of the ``k`` smallest
    keys ordered by (key, index), and which of them are candidates."""
    q, m = key.shape
    rows = np.arange(q)[:, None]
    if m <= k:
        idx = np.broadcast_to(np.arange(m), (q, m))
    else:
        part = np.argpartition(key, k - 1, axis=1)[:, :k]
        kth = key[rows, part].max(axis=1, keepdims=True)  # the k-th smallest key
        less, tie = key < kth, key == kth
        need = k - less.sum(axis=1, keepdims=True)
        chosen = less | (tie & (np.cumsum(tie, axis=1) <= need))  # ties: the lowest indices
        idx = np.nonzero(chosen)[1].reshape(q, k)
    idx = idx[rows, np.argsort(key[rows, idx], axis=1, kind="stable")]
    found = np.isfinite(key[rows, idx])
    if m < k:
        idx = np.concatenate([idx, np.zeros((q, k - m), dtype=idx.dtype)], axis=1)
        found = np.concatenate([found, np.zeros((q, k - m), dtype=bool)], axis=1)
    return idx, found


def vector_observations(
    head: np.ndarray,
    origin: np.ndarray,
    state: np.ndarray,
    present: np.ndarray,
    velocity: np.ndarray,
    moved: np.ndarray,
    size: np.ndarray,
    agent: np.ndarray,
    map_points: np.ndarray,
    map_category: np.ndarray,
    map_real: np.ndarray,
    route_ahead: np.ndarray,
    neighbours: int,
    map_points_out: int,
    radius: float,
) -> np.ndarray:
    """``vector`` observations ``[Q, F]`` (layout: :mod:`~trajeglish_env.env.observations`) of agents
    ``agent [Q]`` at ``origin [Q,3]`` with ego features ``head [Q,8]``, each against the picture of its
    own scene, gathered per query: ``state [Q,N,3]``, ``present``/``moved [Q,N]``, ``velocity [Q,N,2]``,
    ``size [Q,N,2]``; map points ``[Q,M,2]`` of ``map_category [Q,M]`` in ascending order of the scene's
    points (``map_real [Q,M]``: not padding), every point within ``radius`` among them;
    ``route_ahead [Q,R,2]`` global route points."""
    q, n = present.shape
    rel = to_local(origin[:, None, :], state)
    dist = np.hypot(rel[..., 0], rel[..., 1])
    cand = present & (dist <= radius) & (np.arange(n)[None] != agent[:, None])
    near, found = nearest_first(np.where(cand, dist, np.inf), neighbours)
    rows = np.arange(q)[:, None]
    r, v, sz = rel[rows, near], velocity[rows, near], size[rows, near]
    c, s = np.cos(origin[:, 2])[:, None], np.sin(origin[:, 2])[:, None]
    feats = np.stack(
        [
            np.ones(near.shape),
            r[..., 0] / radius,
            r[..., 1] / radius,
            np.cos(r[..., 2]),
            np.sin(r[..., 2]),
            (c * v[..., 0] + s * v[..., 1]) / 30.0,
            (-s * v[..., 0] + c * v[..., 1]) / 30.0,
            sz[..., 0] / 10.0,
            sz[..., 1] / 5.0,
            moved[rows, near].astype(np.float64),
        ],
        axis=-1,
    )
    feats = np.where(found[..., None], feats, 0.0)
    # map points: nearest within the radius, in the agent's frame
    mp = np.zeros((q, map_points_out, 6))
    if map_points.shape[1]:
        dx, dy = map_points[..., 0] - origin[:, None, 0], map_points[..., 1] - origin[:, None, 1]
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        d2 = lx * lx + ly * ly
        pick, inside = nearest_first(np.where(map_real & (d2 <= radius * radius), d2, np.inf), map_points_out)
        cat = map_category[rows, pick]
        mp[..., 0] = 1.0
        mp[..., 1] = lx[rows, pick] / radius
        mp[..., 2] = ly[rows, pick] / radius
        mp[..., 3], mp[..., 4], mp[..., 5] = cat == LANE, cat == LINE, cat == EDGE
        mp = np.where(inside[..., None], mp, 0.0)
    d = route_ahead - origin[:, None, :2]
    route = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1) / radius
    out = np.concatenate([head, feats.reshape(q, -1), mp.reshape(q, -1), route.reshape(q, -1)], axis=1)
    return np.clip(out, -1.0, 1.0).astype(np.float32)
