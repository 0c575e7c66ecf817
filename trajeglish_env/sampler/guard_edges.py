"""Road edges of guarded sampling: which sampled vehicles a candidate could take off the road, and the env's
off-road rule for their candidate boxes (a corner more than the margin beyond a road edge, the edge chosen
and signed as the WOSAC reference does: :mod:`~trajeglish_env.batch_geometry`).

A vehicle is left unchecked only where no candidate can be off the road, which is proved, not assumed: on
a flat map, every segment that can be nearest to a point of a disc holding all its candidates' corners has
the whole disc on its road side (the sign rule then gives every corner a distance <= 0). Each row-agent
keeps a list of the segments near an anchor point (re-chosen when it drifts away), and the proof at the
anchor covers every position within the drift; the nearest segments are sought among those of the list
that can be nearest to a corner (bounded by the corner's distance to a few probe segments).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.batch_geometry import (
    nearest_segments_near,
    pad_stack,
    point_segment_distances,
    selection_d2,
    signed_distances_to,
)
from trajeglish_env.sampler.rows import RowEdges, RowStates

# A row-agent's list holds the segments within its reach of its anchor, re-chosen when the agent is farther
# than EDGE_DRIFT m from it. The reach is what a position within the drift can need (the anchor's clearance,
# twice the drift and the candidates' extent, LIST_SLACK m more for the corner search), at most EDGE_REACH m:
# on the shared WOMD scene's city map that is 40 % fewer segments a vehicle than a fixed 40 m.
EDGE_REACH, EDGE_DRIFT, LIST_SLACK = 40.0, 6.0, 4.0
# A list is chosen among the segments within GRID_REACH m of the square grid cell (GRID_CELL m) of its
# anchor, found once per cell, instead of among every segment of the scene (the shared WOMD scene has
# 5,251). The list's proof (see EdgeLists) sees those segments: enough for a vehicle up to about 17 m from
# the nearest edge (one farther away is proved at each call instead, see road_view).
GRID_CELL, GRID_REACH = 10.0, EDGE_REACH
PROBES = 6  # segments nearest a vehicle that bound its candidates' corners' distances to the road edges
_SLACK = 0.01  # metres of slack in the proofs, covering the reference's float32 rounding


def segment_geometry(
    columns: np.ndarray, rows: np.ndarray, index: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """2-D distances ``[n,K]`` from ``points [n,2]`` to the segments ``index [n,K]`` (-1: none, inf) of rows
    ``rows [n]`` of the padded road edges ``columns [B,7,S]``, and the points' signed distances to the
    segments' lines (negative on the left, the road side; -inf for none and for null segments)."""
    safe = np.maximum(index, 0)
    ax, ay, dx, dy = (columns[rows[:, None], k, safe].astype(np.float64) for k in (0, 1, 3, 4))
    ux, uy = points[:, 0, None] - ax, points[:, 1, None] - ay
    length2 = dx * dx + dy * dy
    real = length2 > 0
    unit = np.where(real, length2, 1.0)
    t = np.clip(np.where(real, (ux * dx + uy * dy) / unit, 0.0), 0, 1)
    distance = np.where(index >= 0, np.hypot(ux - t * dx, uy - t * dy), np.inf)
    side = np.where((index >= 0) & real, (ux * dy - uy * dx) / np.sqrt(unit), -np.inf)
    return distance, side


def on_road_side(
    distance: np.ndarray, side: np.ndarray, clearance: np.ndarray, radius: np.ndarray, cover: np.ndarray
) -> np.ndarray:
    """``[n]`` True where a disc of ``radius [n]`` around a point (at ``clearance [n]`` from the nearest
    edge) lies on the road side of every segment that can be nearest to one of its points (those within
    clearance + 2 radius of the centre, all among the listed ones if that is within ``cover [n]``): the
    reference's distance is then <= 0 all over the disc (beyond a segment's end, the neighbour that gives
    the sign is as near)."""
    reach = clearance + 2 * radius + _SLACK
    relevant = distance <= reach[:, None]
    return (reach <= cover) & (~relevant | (side <= -(radius + _SLACK)[:, None])).all(axis=1)


def is_flat(edges: RowEdges) -> bool:
    """Every road-edge point of a row at z = 0 (the generated maps): the reference's choice of the nearest
    segment is then the planar one, which the proofs above need."""
    columns = edges[0]
    return not (columns[2].any() or columns[5].any())


class SegmentGrid:
    """The road-edge segments (``columns [7,S]``) near each square cell of ``cell`` m: every segment within
    ``reach`` m of some point of the cell is among them (they are those within ``reach`` plus half the
    cell's diagonal of its centre), found when the cell is first asked for."""

    def __init__(self, columns: np.ndarray, reach: float, cell: float = GRID_CELL):
        self.columns, self.cell = columns, float(cell)
        self.radius = float(reach) + self.cell * np.sqrt(0.5) + _SLACK
        self.cells: dict[tuple[int, int], np.ndarray] = {}

    def near(self, point: np.ndarray) -> np.ndarray:
        """Ascending indices of the segments near the cell of ``point [2]``."""
        key = (int(np.floor(point[0] / self.cell)), int(np.floor(point[1] / self.cell)))
        hit = self.cells.get(key)
        if hit is None:
            centre = (np.array(key, dtype=np.float64) + 0.5) * self.cell
            distances = point_segment_distances(self.columns, centre)
            hit = self.cells[key] = np.flatnonzero(distances <= self.radius)
        return hit


class EdgeLists:
    """Per row-agent: the road-edge segments within ``reach`` of an anchor point, and whether every
    candidate box from any position within EDGE_DRIFT of it is provably on the road (``sure``)."""

    def __init__(self) -> None:
        self.anchor = np.zeros((0, 0, 2))
        self.reach = np.zeros((0, 0))
        self.lists = np.zeros((0, 0, 0), dtype=np.int32)
        self.sure = np.zeros((0, 0), bool)
        self.keys: list[object] = []
        self.flat: dict[int, tuple[RowEdges, bool]] = {}
        self.grids: dict[int, tuple[RowEdges, SegmentGrid]] = {}

    def grid(self, edges: RowEdges) -> SegmentGrid:
        """The :class:`SegmentGrid` of a row's road edges (cached per edge set)."""
        hit = self.grids.get(id(edges))
        if hit is None or hit[0] is not edges:
            if len(self.grids) > 256:
                self.grids.clear()
            hit = self.grids[id(edges)] = (edges, SegmentGrid(edges[0], GRID_REACH))
        return hit[1]

    def row_flat(self, rs: RowStates, rows: np.ndarray) -> np.ndarray:
        """``[n]`` whether the road edges of ``rows`` are flat (cached per edge set)."""
        out = np.zeros(len(rows), bool)
        for i, r in enumerate(rows.tolist()):
            edges = rs.edges[r]
            hit = self.flat.get(id(edges))
            if hit is None or hit[0] is not edges:
                hit = self.flat[id(edges)] = (edges, is_flat(edges))
            out[i] = hit[1]
        return out

    def update(
        self,
        rs: RowStates,
        columns: np.ndarray,
        rr: np.ndarray,
        who: np.ndarray,
        origin: np.ndarray,
        extent: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Lists ``[n,W]``, anchors ``[n,2]``, ``sure [n]`` and the lists' reaches ``[n]`` (every segment
        that near the anchor is listed) of agents ``who`` of rows ``rr`` at ``origin [n,3]`` whose candidate
        corners lie within ``extent [n]`` of it; the lists of agents that drifted away, or of rows now on
        another scene, are chosen anew (around the agent)."""
        B, N = rs.B, rs.N
        if self.anchor.shape[:2] != (B, N):
            self.anchor = np.full((B, N, 2), np.inf)
            self.reach = np.zeros((B, N))
            self.lists = np.full((B, N, 1), -1, dtype=np.int32)
            self.sure = np.zeros((B, N), bool)
            self.keys = [None] * B
        for r in range(B):
            if self.keys[r] is not rs.edges[r]:
                self.anchor[r], self.keys[r] = np.inf, rs.edges[r]
        anchor = self.anchor[rr, who]
        stale = np.flatnonzero(~(np.hypot(*(origin[:, :2] - anchor).T) <= EDGE_DRIFT))
        if len(stale):
            r, a = rr[stale], who[stale]
            # every segment within GRID_REACH of an anchor is near its grid cell
            near = pad_stack(
                [self.grid(rs.edges[i]).near(p) for i, p in zip(r.tolist(), origin[stale, :2], strict=True)],
                -1,
            )
            distance, side = segment_geometry(columns, r, near, origin[stale, :2])
            nearest = distance.min(axis=1, initial=np.inf)
            reach = np.minimum(nearest + 2 * (EDGE_DRIFT + extent[stale]) + LIST_SLACK, EDGE_REACH)
            lists = _compact(distance <= reach[:, None], near)
            if lists.shape[1] > self.lists.shape[2]:
                grown = np.full((B, N, lists.shape[1]), -1, dtype=np.int32)
                grown[..., : self.lists.shape[2]] = self.lists
                self.lists = grown
            self.lists[r, a] = -1
            self.lists[r, a, : lists.shape[1]] = lists
            self.anchor[r, a], self.reach[r, a] = origin[stale, :2], reach
            radius = EDGE_DRIFT + extent[stale]
            cover = np.full(len(stale), GRID_REACH)  # every segment this near was scanned
            clearance = np.minimum(nearest, cover)
            proof = on_road_side(distance, side, clearance, radius, cover)
            self.sure[r, a] = proof & self.row_flat(rs, r)
        return self.lists[rr, who], self.anchor[rr, who], self.sure[rr, who], self.reach[rr, who]


@dataclass(frozen=True)
class RoadView:
    """The road edges of a call's ``n`` pairs: ``road [n]`` where the road-edge rule applies (a vehicle
    that a candidate could take off the road, or farther off it) and ``limit [n]`` how far (m) a candidate
    box's corner may then lie beyond a road edge; each pair's listed segments ``segments [n,W]`` (-1
    padding) with their distances to its origin ``distance [n,W]``, its distance to the nearest edge
    ``clearance [n]`` and ``cover [n]`` (every segment that near its origin is listed); the rows' padded
    road edges ``columns``/``links``/``count``. Where ``pending [n]``, ``limit`` still waits for how far the
    pair's current box ``box [n,4,2]`` lies beyond an edge: the first check of its candidates measures it
    in the same pass (:meth:`beyond`)."""

    road: np.ndarray
    limit: np.ndarray
    segments: np.ndarray
    distance: np.ndarray
    clearance: np.ndarray
    cover: np.ndarray
    columns: np.ndarray
    links: np.ndarray
    count: np.ndarray
    pending: np.ndarray | None = None
    box: np.ndarray | None = None

    def excess(
        self, sel: np.ndarray, rows: np.ndarray, origin: np.ndarray, corners: np.ndarray
    ) -> np.ndarray:
        """``[m,c]`` how far (m) the most off-road corner of a vehicle box lies beyond a road edge (``corners
        [m,c,4,2]``; pairs ``sel [m]`` of rows ``rows [m]``, boxes starting from ``origin [m,3]``; negative:
        on the road): the env's signed distance, the nearest segment sought among those that can be
        nearest to one of the corners."""
        m, c = corners.shape[:2]
        points = corners.reshape(m, c * 4, 2)
        centre = origin[:, :2]
        # an upper bound on each corner's distance to its nearest segment (in the reference's z-stretched
        # metric, never below the planar one): its distance to the PROBES listed segments nearest the origin
        distance, segments = self.distance[sel], self.segments[sel]
        k = min(PROBES, segments.shape[1])
        probes = np.take_along_axis(segments, np.argpartition(distance, k - 1, axis=1)[:, :k], 1)
        cols = self.columns[rows[:, None, None], np.arange(7)[None, :, None], np.maximum(probes, 0)[:, None]]
        d2 = np.where((probes >= 0)[:, None], selection_d2(cols, points[..., 0], points[..., 1]), np.inf)
        bound = np.sqrt(d2.min(axis=-1).astype(np.float64))  # [m, 4c]
        away = np.hypot(points[..., 0] - centre[:, None, 0], points[..., 1] - centre[:, None, 1])
        # so each corner's nearest segment lies within away + bound of the origin; nearest_segments_near
        # keeps 1 m of its reach for float32 rounding (the reach gives it that, and 0.1 m more, so that the
        # farthest corner is decided by the list too); past the list's cover it scans every segment
        reach = np.minimum((away + bound).max(axis=1) + 1.1, self.cover[sel])
        near = _compact(distance <= reach[:, None], segments)
        nearest = nearest_segments_near(self.columns, self.count, rows, points, near, centre, reach[:, None])
        signed = signed_distances_to(self.columns, self.links, rows, points, nearest)
        return signed.reshape(m, c, 4).max(axis=-1)

    def beyond(
        self, sel: np.ndarray, rows: np.ndarray, origin: np.ndarray, corners: np.ndarray
    ) -> np.ndarray:
        """``[m,c]`` True where a candidate box (as in :meth:`excess`) has a corner more than its pair's
        ``limit`` beyond a road edge (a pending limit is measured first, with the candidates)."""
        if self.pending is None or self.box is None or not self.pending[sel].any():
            return self.excess(sel, rows, origin, corners) > self.limit[sel][:, None]
        both = self.excess(sel, rows, origin, np.concatenate([self.box[sel][:, None], corners], axis=1))
        wait = self.pending[sel]
        self.limit[sel[wait]] = np.maximum(self.limit[sel[wait]], both[wait, 0])
        self.pending[sel[wait]] = False
        return both[:, 1:] > self.limit[sel][:, None]


def road_view(
    lists: EdgeLists,
    rs: RowStates,
    rr: np.ndarray,
    who: np.ndarray,
    origin: np.ndarray,
    corners: np.ndarray,
    extent: np.ndarray,
    vehicle: np.ndarray,
    padded: tuple[np.ndarray, np.ndarray, np.ndarray],
    margin: float,
) -> RoadView:
    """The road edges of pairs (agents ``who`` of rows ``rr`` at ``origin [n,3]``, their boxes there
    ``corners [n,4,2]``, their candidates' corners within ``extent [n]``; ``vehicle [n]``) given the rows'
    padded road edges ``padded = (columns, links, count)``: the rule applies to a vehicle unless its
    candidates are provably on the road; a candidate corner may lie ``margin`` m beyond a road edge, or as
    far as the vehicle's box lies already if that is farther (a vehicle off the road may not go farther
    off; measured with its first candidates)."""
    columns, links, count = padded
    n = len(rr)
    road, clearance, cover = np.zeros(n, bool), np.full(n, np.inf), np.zeros(n)
    limit = np.full(n, float(margin))
    segments, distance = np.full((n, 1), -1, dtype=np.int64), np.full((n, 1), np.inf)
    view = RoadView(road, limit, segments, distance, clearance, cover, columns, links, count)
    v = np.flatnonzero(vehicle & (count[rr] > 0))
    if not len(v):
        return view
    listed, anchor, sure, reach = lists.update(rs, columns, rr[v], who[v], origin[v], extent[v])
    c, listed, anchor, reach = v[~sure], listed[~sure], anchor[~sure], reach[~sure]
    if not len(c):
        return view
    listed = listed[:, : max(int((listed >= 0).sum(axis=1).max()), 1)]  # lists are left-packed
    dist, side = segment_geometry(columns, rr[c], listed, origin[c, :2])
    cover[c] = reach - np.hypot(*(origin[c, :2] - anchor).T)  # every segment this near is listed
    clearance[c] = np.minimum(dist.min(axis=1), cover[c])  # exact when below the cover
    proof = on_road_side(dist, side, clearance[c], extent[c], cover[c]) & lists.row_flat(rs, rr[c])
    segments = np.full((n, listed.shape[1]), -1, dtype=np.int64)
    distance = np.full((n, listed.shape[1]), np.inf)
    segments[c], distance[c] = listed, dist
    road[c[~proof]] = True  # their limits are measured with their first candidates (RoadView.beyond)
    return RoadView(
        road, limit, segments, distance, clearance, cover, columns, links, count, road.copy(), corners
    )


def _compact(keep: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Rows of ``index [n,K]`` reduced to their kept entries (ascending order kept), -1 padding."""
    width = max(int(keep.sum(axis=1).max(initial=0)), 1)
    out = np.full((len(keep), width), -1, dtype=np.int64)
    i, j = np.nonzero(keep)
    out[i, (np.cumsum(keep, axis=1) - 1)[i, j]] = index[i, j]
    return out
