"""WOMD-like map polylines and traffic-signal links extracted from a parsed SUMO network.

What the map holds (all polylines resampled at ``spacing`` metres, crosswalks as closed polygons):

- lane centre lines: every vehicle lane of a normal edge (``LANE_SURFACE_STREET``; bike-only lanes
  ``LANE_BIKE``) and, through junctions, one polyline per movement (SUMO's internal lanes of one
  connection joined). Sidewalks and walking areas are not lanes and are left out (the curb that
  separates them from the road is a road edge, and crossings are crosswalks).
- road lines: the boundary between two same-direction lanes (``BROKEN_SINGLE_WHITE``, or
  ``SOLID_SINGLE_WHITE`` next to a bike lane) and the centre line between the two directions of a
  two-way road (``SOLID_DOUBLE_YELLOW``, emitted once per road).
- road edges: ``ROAD_EDGE_BOUNDARY`` for the curb on the right of every edge's rightmost vehicle lane,
  the left side of one-way roads, and, inside junctions, the curb around each corner: the right
  boundary of the rightmost movement (right turn, else straight on) leaving each incoming edge's
  rightmost lane, so intersections are bounded corner to corner and open where roads continue;
  ``ROAD_EDGE_MEDIAN`` around the gap SUMO leaves between the two directions of a road whose lanes
  are not adjacent (beside turn pockets): both sides joined at the tips into a closed island. Every
  edge keeps the road on its left (the WOSAC off-road convention).
- crosswalks (``CROSSWALK``): the rectangle of every SUMO pedestrian crossing.

Signals: one per signalized vehicle movement, keyed by the ``map_id`` of the movement's lane polyline,
with the stop point at the end of the incoming lane (WOMD's convention for lane states).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.geometry import resample_polyline
from trajeglish_env.scenario import ROAD_EDGE_KINDS, MapKind, SignalState
from trajeglish_env.sources.sumo_net import Connection, Lane, SumoNet

_MIN_SEGMENT = 1e-6
_MEDIAN_WIDTH = 4.5  # opposite lanes at most this far apart (m) are separated by a median, not the roadside
# Open road edges shorter than this (m) are left out: SUMO trims an edge between two close junctions to a
# few centimetres, and the right curb of such an edge is a stub pointing into the junction, whose open end
# makes a wedge of the junction "off the road" under the off-road rule (its sign beyond a segment's end
# comes from that segment's line), where logged vehicles drive and guarded ones then may not (random
# networks: 17 stubs a scene, 0.8 % of their lane-centre points off the road; docs/evaluation.md, stop 57).
_MIN_CURB = 1.0
_JOIN_GAP = 0.25  # m: road edges whose end and start lie this close are one curb (chain_road_edges)
_HOOK_REACH = 2.5  # m: a road edge winding more than half a circle within this arc is a hook (despike)
_HOOK_EXCESS = 0.3  # rad beyond pi: median islands and slivers turn exactly pi at their tips (kept)
_MIN_MEDIAN_WIDTH = 0.5  # facing median sides closer than this (m) touch: the directions simply meet

# SUMO link-state characters -> WOMD lane signal states.
SIGNAL_CHARS = {
    "G": SignalState.GO,  # green, priority
    "g": SignalState.GO,  # green, must yield (permissive)
    "y": SignalState.CAUTION,
    "Y": SignalState.CAUTION,
    "u": SignalState.CAUTION,  # red-yellow: about to turn green
    "r": SignalState.STOP,
    "s": SignalState.FLASHING_STOP,  # green right turn on red: stop, then go
    "o": SignalState.FLASHING_CAUTION,  # signal off, blinking
    "O": SignalState.UNKNOWN,  # signal off
}


@dataclass(frozen=True)
class NetworkMap:
    """All map polylines of a network, ragged (like Scenario's map arrays), plus its signal links."""

    points: np.ndarray  # [P,2]
    offsets: np.ndarray  # [K+1]
    kind: np.ndarray  # [K] int8 MapKind
    map_id: np.ndarray  # [K] int64
    signal_tls: tuple[str, ...]  # [L] traffic-light id of each signalized movement
    signal_link: np.ndarray  # [L] int64 link index within its traffic light's state string
    signal_lane_id: np.ndarray  # [L] int64 map_id of the movement's lane polyline
    signal_xy: np.ndarray  # [L,2] stop point

    def polyline_min_distance(self, centre: np.ndarray) -> np.ndarray:
        """Distance ``[K]`` from ``centre [2]`` to the nearest point of each polyline."""
        if len(self.kind) == 0:
            return np.zeros(0)
        dist = np.linalg.norm(self.points - centre, axis=1)
        return np.minimum.reduceat(dist, self.offsets[:-1])


def offset_polyline(points: np.ndarray, offset: float) -> np.ndarray:
    """Shift a polyline ``[n,2]`` sideways by ``offset`` metres (positive = left of its direction), mitred."""
    points = np.asarray(points, dtype=np.float64)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > _MIN_SEGMENT])
    points = points[keep]
    if len(points) < 2:
        return points.copy()
    direction = np.diff(points, axis=0)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)  # [n-1,2], left normals
    before = np.concatenate([normal[:1], normal])  # segment normal before each vertex
    after = np.concatenate([normal, normal[-1:]])  # and after it
    # Mitre vector (n1 + n2) / (1 + n1.n2): unit offset along both adjacent segments; clipped at sharp turns.
    denom = np.maximum(1.0 + np.sum(before * after, axis=1, keepdims=True), 0.5)
    return points + offset * (before + after) / denom


class _MapBuilder:
    """Collects polylines with their kinds; ids are consecutive integers in insertion order."""

    def __init__(self, spacing: float) -> None:
        self.spacing = spacing
        self.lines: list[np.ndarray] = []
        self.kinds: list[int] = []

    def add(self, points: np.ndarray, kind: MapKind, resample: bool = True) -> int:
        """Add a polyline of ``kind``; returns its map id, or -1 for an open road edge shorter than
        :data:`_MIN_CURB` (left out, see there)."""
        points = resample_polyline(points, self.spacing) if resample else np.asarray(points, np.float64)
        if kind in ROAD_EDGE_KINDS and _stub(points):
            return -1
        self.lines.append(points)
        self.kinds.append(int(kind))
        return len(self.lines) - 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``points, offsets, kinds, ids`` of the polylines, road edges that meet end to start chained
        (:func:`chain_road_edges`), and ``renumber [n]``: the id each id :meth:`add` returned now has."""
        lines, kinds, keep = chain_road_edges(self.lines, self.kinds)
        lines = [
            despike(line) if k in ROAD_EDGE_KINDS else line for line, k in zip(lines, kinds, strict=True)
        ]
        offsets = np.zeros(len(lines) + 1, dtype=np.int64)
        offsets[1:] = np.cumsum([len(p) for p in lines])
        points = np.concatenate(lines) if lines else np.zeros((0, 2))
        ids = np.arange(len(lines), dtype=np.int64)
        renumber = np.where(keep, np.cumsum(keep) - 1, -1)
        return points, offsets, np.asarray(kinds, dtype=np.int8), ids, renumber


def chain_road_edges(
    lines: list[np.ndarray], kinds: list[int]
) -> tuple[list[np.ndarray], list[int], np.ndarray]:
    """Open road edges whose end meets another's start (within :data:`_JOIN_GAP` m, nearest first) joined
    into one polyline, at the place of the chain's first (a chain that comes back to its start is
    closed); returns the lines, their kinds and ``keep [n]`` (False: joined into an earlier one).

    Why: a curb that turns a junction corner arrives as two polylines (an edge's curb, the corner's),
    and the off-road rule signs a point beyond a polyline's end by that end segment's line, so the
    corner of two separate polylines casts a wedge of "off the road" into the junction where one polyline
    is signed by its neighbour segment (docs/evaluation.md, stop 57)."""
    edge = [i for i, k in enumerate(kinds) if k in ROAD_EDGE_KINDS and not _closed(lines[i])]
    keep = np.ones(len(lines), bool)
    if len(edge) < 2:
        return list(lines), list(kinds), keep
    starts = np.array([lines[i][0] for i in edge])
    ends = np.array([lines[i][-1] for i in edge])
    gap = np.linalg.norm(ends[:, None] - starts[None], axis=-1)
    np.fill_diagonal(gap, np.inf)
    successor = np.full(len(edge), -1)
    taken = np.zeros(len(edge), bool)
    near_a, near_b = np.nonzero(gap <= _JOIN_GAP)
    for k in np.argsort(gap[near_a, near_b], kind="stable"):  # nearest pairs first
        a, b = near_a[k], near_b[k]
        if successor[a] < 0 and not taken[b]:
            successor[a], taken[b] = b, True
    out = list(lines)
    done = np.zeros(len(edge), bool)
    heads = [a for a in range(len(edge)) if not taken[a]] + list(range(len(edge)))  # cycles: any member
    for head in heads:
        if done[head] or successor[head] < 0:
            continue
        parts, a = [lines[edge[head]]], head
        done[head] = True
        while successor[a] >= 0 and not done[successor[a]]:
            a = successor[a]
            done[a] = True
            parts.append(lines[edge[a]][1:])
            keep[edge[a]] = False
        chain = np.concatenate(parts)
        if successor[a] == head:  # around and back: a closed curb, its last point (near its first) dropped
            chain = np.concatenate([chain[:-1], chain[:1]])
        out[edge[head]] = chain
    return (
        [line for line, k in zip(out, keep, strict=True) if k],
        [c for c, k in zip(kinds, keep, strict=True) if k],
        keep,
    )


def despike(points: np.ndarray, reach: float = _HOOK_REACH) -> np.ndarray:
    """A road edge without its hooks: a run of vertices within ``reach`` m of arc that turns more than half
    a circle (one way, by a margin: the tips of the generator's median islands turn exactly half a circle)
    is dropped, again until none is left. Why: at an acute block corner of a spider
    network the corner's kerb (an offset of its right-turn lane) starts with a short hook that winds the
    wrong way round, and the off-road rule signs the points beyond a vertex by the turn there: the hook
    flipped a wedge of the junction, up to 15 m deep where logged vehicles drive, to "off the road"
    (stop 79). A real kerb turns that much only over metres (a 2 m island turns 72 degrees in 2.5 m)."""
    points = np.asarray(points, dtype=np.float64)
    while len(points) > 3:
        step = np.diff(points, axis=0)
        length = np.linalg.norm(step, axis=1)
        heading = np.arctan2(step[:, 1], step[:, 0])
        turn = (np.diff(heading) + np.pi) % (2 * np.pi) - np.pi  # at vertices 1 .. n-2
        hook = _first_hook(turn, length, reach)
        if hook is None:
            return points
        points = np.delete(points, np.arange(hook[0] + 1, hook[1] + 2), axis=0)
    return points


def _first_hook(turn: np.ndarray, length: np.ndarray, reach: float) -> tuple[int, int] | None:
    """The first run ``turn[i..j]`` whose vertices lie within ``reach`` m of each other along the line
    and whose turns add up to more than pi; None if there is none."""
    for i in range(len(turn)):
        total, arc = 0.0, 0.0
        for j in range(i, len(turn)):
            if j > i:
                arc += length[j]  # the segment from vertex j to vertex j + 1
                if arc > reach:
                    break
            total += turn[j]
            if abs(total) > np.pi + _HOOK_EXCESS:  # a ring's tip turns exactly pi (plus rounding)
                return i, j
    return None


def _closed(points: np.ndarray) -> bool:
    return len(points) > 2 and bool(np.allclose(points[0], points[-1]))


def _stub(points: np.ndarray) -> bool:
    """Whether a polyline is open and shorter than :data:`_MIN_CURB`."""
    return not _closed(points) and float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) < _MIN_CURB


def _lane_kind(lane: Lane) -> MapKind:
    return MapKind.LANE_BIKE if lane.role == "bike" else MapKind.LANE_SURFACE_STREET


def _joined_shape(lanes: list[Lane]) -> np.ndarray:
    return np.concatenate([lanes[0].shape, *[lane.shape[1:] for lane in lanes[1:]]])


def opposite_partner(
    points: np.ndarray, owner: np.ndarray, direction: np.ndarray, radius: float
) -> np.ndarray:
    """Per point, the lowest other ``owner`` with a point within ``radius`` running the opposite way, else -1.

    A grid hash with cells of ``radius`` compares each point with the points of its 3x3 neighbouring cells.
    """
    cell = np.floor(points / radius).astype(np.int64)
    cell -= cell.min(axis=0) - 1
    stride = int(cell[:, 1].max()) + 2
    key = cell[:, 0] * stride + cell[:, 1]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    partner = np.full(len(points), np.iinfo(np.int64).max)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            probe = key + dx * stride + dy
            lo, hi = np.searchsorted(sorted_key, probe, "left"), np.searchsorted(sorted_key, probe, "right")
            counts = hi - lo
            query = np.repeat(np.arange(len(points)), counts)
            within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
            other = order[np.repeat(lo, counts) + within]
            match = (
                (owner[query] != owner[other])
                & (np.linalg.norm(points[query] - points[other], axis=1) <= radius)
                & (np.sum(direction[query] * direction[other], axis=1) < -0.5)
            )
            np.minimum.at(partner, query[match], owner[other[match]])
    return np.where(partner == np.iinfo(np.int64).max, -1, partner)


def _runs(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """(label, start, stop) of the runs of equal labels; each run also keeps the first point of the next."""
    cuts = np.flatnonzero(np.diff(labels)) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts + 1, [len(labels)]])
    return [(int(labels[a]), int(a), int(min(b, len(labels)))) for a, b in zip(starts, stops, strict=True)]


def _add_edges(net: SumoNet, builder: _MapBuilder) -> None:
    """Lane centre lines, road lines between lanes, centre lines and curbs of every normal edge.

    The left side of an edge's leftmost lane is the centre line of a two-way road where a lane of the
    opposite direction runs alongside (found geometrically, so it also works where SUMO splits one
    direction for a turn pocket), and a road edge elsewhere.
    """
    left_sides = []
    for edge in net.edges.values():
        lanes = edge.vehicle_lanes
        if not lanes:
            continue
        for lane in lanes:
            builder.add(lane.shape, _lane_kind(lane))
        for right, left in zip(lanes[:-1], lanes[1:], strict=False):
            bike = "bike" in (right.role, left.role)
            line = MapKind.ROAD_LINE_SOLID_SINGLE_WHITE if bike else MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE
            builder.add(offset_polyline(right.shape, 0.5 * right.width), line)
        builder.add(offset_polyline(lanes[0].shape, -0.5 * lanes[0].width), MapKind.ROAD_EDGE_BOUNDARY)
        left_sides.append(
            resample_polyline(offset_polyline(lanes[-1].shape, 0.5 * lanes[-1].width), builder.spacing)
        )
    if not left_sides:
        return
    # Junction movements count as opposite traffic too (not emitted): where a road's lanes end at a
    # junction, the other direction continues through it on internal lanes, and no curb lies between.
    internal = [
        resample_polyline(offset_polyline(lane.shape, 0.5 * lane.width), builder.spacing)
        for lane in net.lanes.values()
        if lane.lane_id.startswith(":") and lane.role in ("drive", "bike") and len(lane.shape) >= 2
    ]
    sides = left_sides + [side for side in internal if len(side) >= 2]
    points = np.concatenate(sides)
    owner = np.repeat(np.arange(len(sides)), [len(side) for side in sides])
    tangent = np.concatenate([np.gradient(side, axis=0) for side in sides])
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), _MIN_SEGMENT)
    normal = owner < len(left_sides)
    partner = opposite_partner(points[normal], owner[normal], tangent[normal], 0.75 * builder.spacing)
    across = opposite_partner(points, owner, tangent, radius=_MEDIAN_WIDTH)[normal]
    owner = owner[normal]
    # Per point: the shared centre line, emitted by the lower-numbered edge of the pair (1) or by its
    # partner (0); the edge of a median (opposite lanes further apart, e.g. beside SUMO's turn pockets,
    # 2); or the outer boundary of a one-way road (3).
    label = np.where(partner >= 0, (partner > owner).astype(np.int64), np.where(across >= 0, 2, 3))
    kinds = {
        1: MapKind.ROAD_LINE_SOLID_DOUBLE_YELLOW,
        2: MapKind.ROAD_EDGE_MEDIAN,
        3: MapKind.ROAD_EDGE_BOUNDARY,
    }
    medians: dict[tuple[int, int], list[np.ndarray]] = {}
    start = 0
    for k, side in enumerate(left_sides):
        for value, a, b in _runs(label[start : start + len(side)]):
            if value == 0 or b - a < 2:
                continue
            # A left side runs with its lanes on its right; road edges keep the road on their left
            # (the off-road metric's convention), so medians and left curbs are reversed.
            run = side[a:b] if value == 1 else side[a:b][::-1]
            if value == 2:
                if np.linalg.norm(np.diff(run, axis=0), axis=1).sum() < _MIN_MEDIAN_WIDTH:
                    continue  # a sliver of a point or two where two roads meet: no island
                opposite = across[start + a : start + b]  # the edge (or junction lane) across the median
                medians.setdefault((k, int(np.bincount(opposite[opposite >= 0]).argmax())), []).append(run)
            else:
                builder.add(run, kinds[value], resample=False)
        start += len(side)
    for island in _median_islands(medians):
        builder.add(island, MapKind.ROAD_EDGE_MEDIAN)


def _median_islands(medians: dict[tuple[int, int], list[np.ndarray]]) -> list[np.ndarray]:
    """Close each median into an island: the reversed left sides of two opposite edges facing each other
    (each ``(edge, partner)`` run matched with the nearest ``(partner, edge)`` run) joined at both tips,
    clockwise, so the road lies outside it also beyond its ends, where traffic waits at a junction. A run
    without a facing run (its opposite edge is split elsewhere) becomes a thin island of its own."""
    islands = []
    for (edge, partner), runs in medians.items():
        if edge > partner and (partner, edge) in medians:
            continue  # joined when its partner's runs were visited
        facing = list(medians.get((partner, edge), [])) if edge < partner else []
        for run in runs:
            if not facing:
                islands.append(_sliver(run))
                continue
            # this run goes from tip p to tip q; the facing run (opposite traffic) from q to p
            gap = [
                np.linalg.norm(other[0] - run[-1]) + np.linalg.norm(other[-1] - run[0]) for other in facing
            ]
            other = facing.pop(int(np.argmin(gap)))
            apart = np.linalg.norm(run[:, None] - other[None], axis=-1).min(axis=1)
            if np.median(apart) >= _MIN_MEDIAN_WIDTH:  # else the two sides touch: no island between them
                islands.append(_ring_from_middle(np.concatenate([run, other]), len(run) // 2))
        islands.extend(_sliver(run) for run in facing)
    return islands


def _sliver(run: np.ndarray, width: float = 0.2) -> np.ndarray:
    """A closed island ``width`` m wide on the right of ``run`` (which keeps the road on its left)."""
    return _ring_from_middle(np.concatenate([run, offset_polyline(run, -width)[::-1]]), len(run) // 2)


def _ring_from_middle(loop: np.ndarray, start: int) -> np.ndarray:
    """The closed ring of the points ``loop [n,2]`` (in order, not repeated) starting and ending at
    ``start``, the middle of a side: the off-road rule (the WOSAC reference) treats a ring as open unless
    it is the map's longest road edge, so its ends are signed by their own segments' lines, which at an
    island's tip cast a spike of "off the road" into the junction, and along a side continue the side."""
    return np.concatenate([loop[start:], loop[:start], loop[start : start + 1]])


_CURB_PREFERENCE = {"R": 0, "r": 0, "s": 1}


def _add_junctions(net: SumoNet, builder: _MapBuilder) -> dict[str, int]:
    """Lane polylines of every vehicle movement through a junction and the curbs around each corner.

    Returns the map id of each movement's lane, keyed by its first internal lane.
    """
    movement_id: dict[str, int] = {}
    corner: dict[str, tuple[int, Connection]] = {}
    for conn in net.connections:
        edge = net.edges.get(conn.from_edge)
        target = net.edges.get(conn.to_edge)
        if edge is None or target is None or not conn.via or conn.via in movement_id:
            continue
        chain = net.internal_chain(conn.via)
        if chain[0].role not in ("drive", "bike"):
            continue
        movement_id[conn.via] = builder.add(_joined_shape(chain), _lane_kind(chain[0]))
        rightmost = edge.vehicle_lanes[0].index
        rank = _CURB_PREFERENCE.get(conn.direction)
        if conn.from_lane == rightmost and rank is not None:
            if conn.from_edge not in corner or rank < corner[conn.from_edge][0]:
                corner[conn.from_edge] = (rank, conn)
    for _, conn in corner.values():
        chain = net.internal_chain(conn.via)
        builder.add(offset_polyline(_joined_shape(chain), -0.5 * chain[0].width), MapKind.ROAD_EDGE_BOUNDARY)
    return movement_id


def _add_crosswalks(net: SumoNet, builder: _MapBuilder) -> None:
    for lane in net.lanes.values():
        if lane.role != "crossing":
            continue
        ends = lane.shape[[0, -1]]
        left = offset_polyline(ends, 0.5 * lane.width)
        right = offset_polyline(ends, -0.5 * lane.width)
        polygon = np.concatenate([right, left[::-1], right[:1]])
        builder.add(polygon, MapKind.CROSSWALK, resample=False)


def build_network_map(net: SumoNet, spacing: float = 1.0) -> NetworkMap:
    """All lanes, road lines, road edges, crosswalks and signalized movements of ``net``."""
    builder = _MapBuilder(spacing)
    _add_edges(net, builder)
    movement_id = _add_junctions(net, builder)
    _add_crosswalks(net, builder)
    tls, links, lane_ids, stops = [], [], [], []
    for conn in net.connections:
        if conn.tl and conn.link_index >= 0 and conn.via in movement_id:
            tls.append(conn.tl)
            links.append(conn.link_index)
            lane_ids.append(movement_id[conn.via])
            stops.append(net.lanes[conn.via].shape[0])
    points, offsets, kinds, ids, renumber = builder.arrays()
    lane_ids = [int(renumber[i]) for i in lane_ids]
    return NetworkMap(
        points=points,
        offsets=offsets,
        kind=kinds,
        map_id=ids,
        signal_tls=tuple(tls),
        signal_link=np.asarray(links, dtype=np.int64),
        signal_lane_id=np.asarray(lane_ids, dtype=np.int64),
        signal_xy=np.asarray(stops, dtype=np.float64).reshape(-1, 2),
    )


def signal_states(state_strings: np.ndarray, links: np.ndarray) -> np.ndarray:
    """SignalState codes for link indices ``links [L]`` of SUMO state strings ``state_strings [T]``."""
    lookup = np.zeros(256, dtype=np.int8)
    for char, state in SIGNAL_CHARS.items():
        lookup[ord(char)] = int(state)
    if len(state_strings) == 0 or len(links) == 0:
        return np.zeros((len(state_strings), len(links)), dtype=np.int8)
    codes = np.frombuffer("".join(state_strings).encode("ascii"), dtype=np.uint8)
    width = len(state_strings[0])
    if len(codes) != width * len(state_strings) or links.max() >= width:
        raise ValueError(f"traffic-light states: expected equal-length strings covering link {links.max()}")
    return lookup[codes.reshape(len(state_strings), width)[:, links]]
