"""Signed distance to the road edges and the off-road indicator (WOSAC §2.4), exact and fast.

Road edges are polylines with the drivable area on their left; the distance is negative on the road and
positive off it. For each query point the reference picks the segment nearest in 3-D (z stretched by
3, see :data:`Z_STRETCH`), reports the 2-D distance to it and takes the sign from that segment, or,
beyond a segment's end, from the convexity of the vertex it shares with its neighbour.

Speed: nested uniform grids (:mod:`trajeglish_env.metrics.grid`). Each occupied cell gets the list of
the segments that can be nearest (in 2-D) to some point of the cell; a query then only scans its cell's
list. A query whose 3-D answer is not provably inside the list (z far from the map's) falls back to a
scan of every segment, so the result is always the exhaustive one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from trajeglish_env.metrics.grid import CellLists, build_cell_lists

__all__ = [
    "INVALID_DISTANCE",
    "RoadEdges",
    "Z_STRETCH",
    "box_bottom_corners",
    "distance_to_road_edge",
    "signed_distance_to_road_edges",
]

Z_STRETCH = np.float32(3.0)  # vertical distances weigh 3x when choosing the nearest segment
CYCLIC_GAP_SQUARED = 1.0  # a polyline whose ends are closer than 1 m (squared: 1 m^2) is closed
INVALID_DISTANCE = -1e10  # distance reported for invalid object states
OFFROAD_THRESHOLD = 0.0  # off-road iff distance > this
_FALLBACK_PAIRS = 1 << 20  # query x segment pairs per chunk of the exhaustive scan
_QUERY_PAIRS = 1 << 15  # query x candidate pairs per chunk of the grid scan
_DIRECT_PAIRS = 1 << 16  # below this many query x segment pairs a plain scan beats building a grid
_GROUP_WIDTH = 8  # queries are grouped by list length rounded up to a multiple of this


@dataclass(frozen=True, eq=False)
class RoadEdges:
    """All road-edge segments, in (polyline, segment) order, with their neighbours along the polyline.

    ``start``/``end [S, 3]`` float32 (x, y, z); ``previous``/``following [S]`` index of the neighbouring
    segment or -1 (closed polylines wrap around, see :meth:`from_polylines`).
    """

    start: np.ndarray
    end: np.ndarray
    previous: np.ndarray
    following: np.ndarray

    @property
    def num_segments(self) -> int:
        return int(self.start.shape[0])

    @cached_property
    def columns(self) -> np.ndarray:
        """``[7, S]`` float32 rows: start x, y, z, direction x, y, z, 1 / squared 2-D length (0 if null)."""
        direction = self.end - self.start
        length2 = direction[:, 0] ** 2 + direction[:, 1] ** 2
        with np.errstate(divide="ignore"):
            inverse = np.where(length2 > 0, np.float32(1) / length2, np.float32(0))
        return np.ascontiguousarray(np.vstack([self.start.T, direction.T, inverse[None]]).astype(np.float32))

    @cached_property
    def convex_start(self) -> np.ndarray:
        """``[S]`` True where a segment turns left from its predecessor: a convex vertex of the road."""
        direction = self.end - self.start
        before = direction[np.maximum(self.previous, 0)]
        turn = _cross(before[:, 0], before[:, 1], direction[:, 0], direction[:, 1])
        return (turn > 0) & (self.previous >= 0)

    @cached_property
    def is_flat(self) -> bool:
        """True when every edge point has z = 0 (generated 2-D maps)."""
        return not (self.start[:, 2].any() or self.end[:, 2].any())

    @cached_property
    def planar_columns(self) -> np.ndarray:
        """The rows of :attr:`columns` that planar queries need (start x, y, direction x, y, inverse)."""
        return np.ascontiguousarray(self.columns[_FLAT_ROWS])

    @classmethod
    def from_polylines(cls, polylines: Sequence[np.ndarray]) -> RoadEdges:
        """Segments of ``polylines`` (each ``[n, 2]`` or ``[n, 3]``, road on the left).

        Polylines with fewer than 2 points are dropped. As in the reference, a polyline wraps around
        (its first segment follows its last) only if its ends are less than 1 m apart and it has as
        many points as the longest road-edge polyline; other polylines are open.
        """
        lines = []
        for k, line in enumerate(polylines):
            line = np.asarray(line, dtype=np.float64)
            if line.ndim != 2 or line.shape[1] not in (2, 3) or not np.isfinite(line).all():
                raise ValueError(f"road edge polyline {k}: expected finite points [n, 2|3], got {line.shape}")
            if line.shape[1] == 2:
                line = np.concatenate([line, np.zeros((len(line), 1))], axis=1)
            if len(line) >= 2:
                lines.append(line.astype(np.float32))
        if not lines:
            raise ValueError(
                "the scene has no road edge with at least 2 points (needed for off-road metrics)"
            )
        longest = max(len(line) for line in lines)
        counts = np.array([len(line) - 1 for line in lines])
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        last = first + counts - 1
        index = np.arange(counts.sum())
        previous, following = index - 1, index + 1
        previous[first], following[last] = -1, -1
        for k, line in enumerate(lines):
            gap = line[0] - line[-1]
            if len(line) == longest and float(np.dot(gap, gap)) < CYCLIC_GAP_SQUARED:
                previous[first[k]], following[last[k]] = last[k], first[k]
        return cls(
            start=np.concatenate([line[:-1] for line in lines]),
            end=np.concatenate([line[1:] for line in lines]),
            previous=previous,
            following=following,
        )


def _cross(ux: np.ndarray, uy: np.ndarray, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
    return ux * vy - uy * vx


_FLAT_ROWS = np.array([0, 1, 3, 4, 6])  # the rows of RoadEdges.columns that planar queries need


def _selection_distance(
    qx: np.ndarray, qy: np.ndarray, qz: np.ndarray | None, columns: Sequence[np.ndarray]
) -> np.ndarray:
    """Squared z-stretched 3-D distance from points (``q* [Q, 1]``, in the frame of ``columns``) to the
    segments ``columns [7 or 5, Q|1, K]`` (rows of :attr:`RoadEdges.columns`; 5 when ``qz`` is None)."""
    if qz is None:
        ax, ay, dx, dy, inverse = columns
    else:
        ax, ay, az, dx, dy, dz, inverse = columns
    ux, uy = qx - ax, qy - ay
    t = np.clip((ux * dx + uy * dy) * inverse, 0, 1)
    rx = ux - t * dx
    ry = uy - t * dy
    out = rx * rx + ry * ry
    if qz is not None:
        rz = Z_STRETCH * (qz - az - t * dz)
        out += rz * rz
    return out


def _nearest_exhaustive(edges: RoadEdges, points: np.ndarray, flat: bool) -> np.ndarray:
    """Index of the nearest segment (3-D, z stretched; first on ties) for each point, scanning all."""
    out = np.empty(len(points), dtype=np.int64)
    step = max(1, _FALLBACK_PAIRS // edges.num_segments)
    columns = (edges.planar_columns if flat else edges.columns)[:, None, :]
    for s in range(0, len(points), step):
        q = points[s : s + step, :, None]
        d2 = _selection_distance(q[:, 0], q[:, 1], None if flat else q[:, 2], columns)
        out[s : s + step] = np.argmin(d2, axis=1)
    return out


def _nearest_with_grid(edges: RoadEdges, points: np.ndarray, lists: CellLists, flat: bool) -> np.ndarray:
    """Nearest segment per point using the cell lists; exhaustive scan where the list is not conclusive.

    Queries are processed in groups of similar list length, so a few long lists (cells far from the
    map) do not widen every query's scan.
    """
    table = edges.planar_columns if flat else edges.columns  # [C, S], small enough to stay in cache
    out = np.empty(len(points), dtype=np.int64)
    length = lists.lengths[lists.query_cell]
    group = (length + _GROUP_WIDTH - 1) // _GROUP_WIDTH
    unsure = []
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        width = int(length[members].max())
        step = max(1, _QUERY_PAIRS // width)
        for s in range(0, len(members), step):
            rows = members[s : s + step]
            cell = lists.query_cell[rows]
            candidates = lists.candidates[cell, :width]
            columns = [np.take(row, candidates) for row in table]
            q = points[rows, :, None]
            d2 = _selection_distance(q[:, 0], q[:, 1], None if flat else q[:, 2], columns)
            best = np.argmin(d2, axis=1)
            pick = np.arange(len(rows))
            out[rows] = candidates[pick, best]
            # Exact when the 3-D minimum lies within the radius the list covers around the query.
            covered = lists.covered_radius[cell]
            unsure.append(rows[d2[pick, best] > covered * covered])
    redo = np.concatenate(unsure) if unsure else np.zeros(0, np.int64)
    if len(redo):
        out[redo] = _nearest_exhaustive(edges, points[redo], flat)
    return out


def _side(qx: np.ndarray, qy: np.ndarray, columns: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Side of the points relative to their ``segment`` lines: -1 left (road side), +1 right, 0 on it."""
    ux, uy = qx - np.take(columns[0], segment), qy - np.take(columns[1], segment)
    return np.sign(_cross(ux, uy, np.take(columns[3], segment), np.take(columns[4], segment)))


def _signed_distance_to(edges: RoadEdges, points: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Signed 2-D distance from ``points [Q, 3]`` to their chosen ``segment [Q]`` (sign by convexity)."""
    columns = edges.columns
    qx, qy = points[:, 0], points[:, 1]
    ux, uy = qx - np.take(columns[0], segment), qy - np.take(columns[1], segment)
    dx, dy = np.take(columns[3], segment), np.take(columns[4], segment)
    length2 = dx * dx + dy * dy
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(length2 > 0, (ux * dx + uy * dy) / length2, np.float32(0))
    tc = np.clip(t, 0, 1)
    rx, ry = ux - tc * dx, uy - tc * dy
    magnitude = np.sqrt(rx * rx + ry * ry)
    sign = np.sign(_cross(ux, uy, dx, dy))  # -1 left (road), +1 right
    # Beyond an end of the segment the sign comes from the vertex shared with the neighbour there:
    # the larger of the two sides at a convex vertex, the smaller at a concave one.
    previous, following = np.take(edges.previous, segment), np.take(edges.following, segment)
    before = (t < 0) & (previous >= 0)
    beyond = np.flatnonzero(before | ((t > 1) & (following >= 0)))
    if len(beyond):
        first = before[beyond]
        other = np.where(first, previous[beyond], following[beyond])
        convex = np.where(first, edges.convex_start[segment[beyond]], edges.convex_start[other])
        own = sign[beyond]
        other_side = _side(qx[beyond], qy[beyond], columns, other)
        sign[beyond] = np.where(convex, np.maximum(own, other_side), np.minimum(own, other_side))
    return sign * magnitude


def signed_distance_to_road_edges(points: np.ndarray, edges: RoadEdges) -> np.ndarray:
    """Signed distance (m, float32) from ``points [..., 3]`` (or ``[..., 2]`` at z = 0) to the road edges.

    Negative on the road side (left of the edges), positive off-road; exactly the exhaustive
    reference rule, accelerated by a grid.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim == 0 or points.shape[-1] not in (2, 3):
        raise ValueError(f"signed_distance_to_road_edges: points must be [..., 2|3], got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("signed_distance_to_road_edges: points must be finite")
    shape = points.shape[:-1]
    flat = points.reshape(-1, points.shape[-1])
    if flat.shape[1] == 2:
        flat = np.concatenate([flat, np.zeros((len(flat), 1), np.float32)], axis=1)
    if len(flat) == 0:
        return np.zeros(shape, np.float32)
    planar = edges.is_flat and not flat[:, 2].any()
    if len(flat) * edges.num_segments <= _DIRECT_PAIRS:  # a few points (an env step): scan every segment
        nearest = _nearest_exhaustive(edges, flat, planar)
    else:
        lists = build_cell_lists(edges.start, edges.end, flat[:, :2], margin=0.0 if planar else 1.5)
        nearest = _nearest_with_grid(edges, flat, lists, planar)
    return _signed_distance_to(edges, flat, nearest).reshape(shape)


def box_bottom_corners(xyz: np.ndarray, heading: np.ndarray, box: np.ndarray) -> np.ndarray:
    """The 4 bottom corners ``[..., 4, 3]`` of boxes with centres ``xyz [..., 3]``, ``heading [...]`` and
    ``box [..., 3]`` (length, width, height) broadcastable to them (float32)."""
    f32 = np.float32
    xyz, heading, box = np.asarray(xyz, f32), np.asarray(heading, f32), np.asarray(box, f32)
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    along = box[..., 0, None] / f32(2) * np.array([1, 1, -1, -1], f32)
    across = box[..., 1, None] / f32(2) * np.array([1, -1, -1, 1], f32)
    x = xyz[..., 0, None] + c * along - s * across
    y = xyz[..., 1, None] + s * along + c * across
    z = np.broadcast_to((xyz[..., 2] - box[..., 2] / f32(2))[..., None], x.shape)
    return np.stack([x, y, z], axis=-1)


def distance_to_road_edge(
    xyz: np.ndarray, heading: np.ndarray, box: np.ndarray, valid: np.ndarray, edges: RoadEdges
) -> np.ndarray:
    """Signed road-edge distance of the most off-road bottom corner of each box, ``[...]`` float32.

    ``xyz [..., 3]``, ``heading [...]``, ``valid [...]``; ``box [..., 3]`` (length, width, height)
    broadcastable. Invalid states get :data:`INVALID_DISTANCE`.
    """
    xyz, heading, valid = (
        np.asarray(xyz, np.float32),
        np.asarray(heading, np.float32),
        np.asarray(valid, bool),
    )
    box = np.broadcast_to(np.asarray(box, np.float32), (*heading.shape, 3))
    out = np.full(heading.shape, np.float32(INVALID_DISTANCE), dtype=np.float32)
    corners = box_bottom_corners(xyz[valid], heading[valid], box[valid])  # invalid states are skipped
    out[valid] = signed_distance_to_road_edges(corners, edges).max(axis=-1)
    return out
