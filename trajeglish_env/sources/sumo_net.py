"""Random urban road networks built with SUMO's ``netgenerate``, and a parsed view of SUMO ``.net.xml`` files.

A network is a grid, spider (rings and radial arms) or random planar graph, always with sidewalks,
pedestrian crossings and (mostly) signalized intersections; size, lane counts, speeds, bike lanes,
turning radii and signal plans are drawn from a seeded NumPy generator so one seed gives one network.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trajeglish_env.sources.sumo_tools import run_tool

NETWORK_KINDS = ("grid", "spider", "random")
DEFAULT_LANE_WIDTH = 3.2  # SUMO's width of a lane without a ``width`` attribute (m)


# ---------------------------------------------------------------------------------------------- generation
def _shared_args(rng: np.random.Generator) -> list[str]:
    """netgenerate options common to all kinds: lanes, speed, sidewalks, crossings, bike lanes, signals."""
    speed = float(rng.choice([8.33, 11.11, 13.89]))
    args = [
        f"--default.lanenumber={int(rng.choice([1, 2, 2, 3]))}",
        f"--default.speed={speed}",
        f"--default.junctions.radius={rng.uniform(4.0, 9.0):.2f}",
        "--sidewalks.guess",
        "--sidewalks.guess.min-speed=0",
        "--sidewalks.guess.max-speed=40",
        f"--default.sidewalk-width={rng.uniform(2.0, 3.0):.2f}",
        "--crossings.guess",
        "--crossings.guess.speed-threshold=40",
        "--no-turnarounds",  # SUMO turns vehicles around on the spot at dead ends
        "--fringe.guess",
        "--junctions.internal-link-detail=20",  # smooth turns: sideways offsets hop at coarse vertices
        f"--tls.default-type={rng.choice(['static', 'static', 'actuated'])}",
        f"--tls.cycle.time={int(rng.integers(50, 91))}",
        "--tls.layout=opposites",  # ("incoming", one approach at a time, leaves most vehicles waiting)
    ]
    # Mostly every intersection signalized; otherwise SUMO guesses which (the rest yield by priority).
    args += (
        ["--default.junctions.type=traffic_light", "--tls.discard-simple"]
        if rng.random() < 0.85
        else ["--tls.guess"]
    )
    if rng.random() < 0.5:
        args.append("--random-lanenumber")
    if rng.random() < 0.35:
        args += ["--bikelanes.guess", "--bikelanes.guess.min-speed=0", "--bikelanes.guess.max-speed=40"]
    if rng.random() < 0.3:
        args.append("--turn-lanes=1")
    return args


def network_args(kind: str, rng: np.random.Generator) -> list[str]:
    """netgenerate arguments for a random network of ``kind`` (``grid``, ``spider`` or ``random``)."""
    if kind == "grid":
        specific = [
            "--grid",
            f"--grid.x-number={int(rng.integers(2, 5))}",
            f"--grid.y-number={int(rng.integers(2, 5))}",
            f"--grid.x-length={rng.uniform(70.0, 130.0):.1f}",
            f"--grid.y-length={rng.uniform(70.0, 130.0):.1f}",
            f"--grid.attach-length={rng.uniform(40.0, 80.0):.1f}",
        ]
    elif kind == "spider":
        specific = [
            "--spider",
            f"--spider.arm-number={int(rng.integers(4, 7))}",
            f"--spider.circle-number={int(rng.integers(2, 4))}",
            f"--spider.space-radius={rng.uniform(45.0, 75.0):.1f}",
            f"--spider.attach-length={rng.uniform(50.0, 80.0):.1f}",
            "--spider.omit-center",
        ]
    elif kind == "random":
        specific = [
            "--rand",
            f"--rand.iterations={int(rng.integers(12, 25))}",
            f"--rand.min-distance={rng.uniform(50.0, 70.0):.1f}",
            f"--rand.max-distance={rng.uniform(90.0, 130.0):.1f}",
            "--rand.min-angle=60",
        ]
        if rng.random() < 0.5:
            specific.append("--rand.grid")
    else:
        raise ValueError(f"unknown SUMO network kind {kind!r}; expected one of {NETWORK_KINDS}")
    return [*specific, *_shared_args(rng), f"--seed={int(rng.integers(0, 2**31 - 1))}"]


def build_network(kind: str, rng: np.random.Generator, workdir: Path) -> Path:
    """Run netgenerate for a random network of ``kind`` in ``workdir``; return the ``.net.xml`` path."""
    path = workdir / "scene.net.xml"
    run_tool(
        "netgenerate", [*network_args(kind, rng), f"--output-file={path.name}", "--no-warnings"], cwd=workdir
    )
    return path


# ---------------------------------------------------------------------------------------------- parsing
@dataclass(frozen=True)
class Lane:
    """One SUMO lane: centre line, width and which road users may use it."""

    lane_id: str
    edge_id: str
    index: int
    shape: np.ndarray  # [n,2] centre line, in driving direction
    width: float
    role: str  # "drive", "bike", "sidewalk", "crossing", "walkingarea"
    length: float  # SUMO's length (positions along the lane are measured in it; may differ from the shape's)


@dataclass(frozen=True)
class Edge:
    """A normal (non-internal) SUMO edge: a one-way road between two junctions, lanes right to left."""

    edge_id: str
    from_node: str
    to_node: str
    lanes: tuple[Lane, ...]

    @property
    def vehicle_lanes(self) -> tuple[Lane, ...]:
        """Lanes usable by vehicles or bicycles (no sidewalks), rightmost first."""
        return tuple(lane for lane in self.lanes if lane.role in ("drive", "bike"))

    @property
    def has_sidewalk(self) -> bool:
        """Whether pedestrians can walk along this edge."""
        return any(lane.role == "sidewalk" for lane in self.lanes)

    @property
    def length(self) -> float:
        """Length of the edge's rightmost lane shape (m)."""
        shape = self.lanes[0].shape
        return float(np.linalg.norm(np.diff(shape, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Connection:
    """A movement from one lane to another across a junction (``via`` is its first internal lane)."""

    from_edge: str
    to_edge: str
    from_lane: int
    to_lane: int
    via: str  # "" when the connection has no internal lane
    tl: str  # controlling traffic light id, "" if unsignalized
    link_index: int
    direction: str  # SUMO dir: s, r, l, t, R, L


@dataclass(frozen=True)
class SumoNet:
    """The parts of a SUMO network the scene source needs: lanes, edges, connections, signals."""

    lanes: dict[str, Lane]
    edges: dict[str, Edge]  # normal edges only
    connections: tuple[Connection, ...]  # connections leaving normal edges (vehicles and pedestrians)
    next_internal: dict[str, str]  # internal lane -> the next internal lane of the same movement
    tls_ids: tuple[str, ...]
    fringe_nodes: frozenset[str]  # junctions at the outer border of the network

    def internal_chain(self, first: str) -> list[Lane]:
        """The internal lanes of one movement, in order, starting at internal lane ``first``."""
        chain = [self.lanes[first]]
        while chain[-1].lane_id in self.next_internal and len(chain) < 8:
            chain.append(self.lanes[self.next_internal[chain[-1].lane_id]])
        return chain

    def fringe_edges(self) -> tuple[list[str], list[str]]:
        """Vehicle edges entering the network from, and leaving it to, its outer fringe (SUMO's guess)."""
        roads = [e for e in self.edges.values() if e.vehicle_lanes]
        return (
            [e.edge_id for e in roads if e.from_node in self.fringe_nodes],
            [e.edge_id for e in roads if e.to_node in self.fringe_nodes],
        )


def _parse_shape(text: str, where: str) -> np.ndarray:
    try:
        points = np.array(
            [[float(v) for v in pair.split(",")[:2]] for pair in text.split()], dtype=np.float64
        )
    except ValueError as error:
        raise ValueError(f"{where}: malformed shape {text[:80]!r}: {error}") from error
    if points.ndim != 2 or len(points) < 2:
        raise ValueError(f"{where}: a lane shape needs at least two points, got {text[:80]!r}")
    return points


def _lane_role(function: str, allow: str, disallow: str) -> str:
    """Classify a lane from its edge function and SUMO permissions."""
    if function in ("crossing", "walkingarea"):
        return function
    allowed = set(allow.split())
    if allowed and allowed <= {"pedestrian"}:
        return "sidewalk"
    if allowed and allowed <= {"bicycle", "pedestrian"} and "bicycle" in allowed:
        return "bike"
    if disallow.split() == ["all"]:
        return "sidewalk"
    return "drive"


def parse_net(path: Path) -> SumoNet:
    """Parse a SUMO ``.net.xml`` file into a :class:`SumoNet` (clear error naming the file if malformed)."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as error:
        raise ValueError(f"{path}: not a valid SUMO network file: {error}") from error
    lanes: dict[str, Lane] = {}
    edges: dict[str, Edge] = {}
    for edge in root.iter("edge"):
        edge_id, function = edge.get("id", ""), edge.get("function", "normal")
        edge_lanes = []
        for lane in edge.iter("lane"):
            lane_id = lane.get("id", "")
            parsed = Lane(
                lane_id=lane_id,
                edge_id=edge_id,
                index=int(lane.get("index", "0")),
                shape=_parse_shape(lane.get("shape", ""), f"{path}: lane {lane_id!r}"),
                width=float(lane.get("width", DEFAULT_LANE_WIDTH)),
                role=_lane_role(function, lane.get("allow", ""), lane.get("disallow", "")),
                length=float(lane.get("length", "0")),
            )
            lanes[lane_id] = parsed
            edge_lanes.append(parsed)
        if function == "normal":
            edge_lanes.sort(key=lambda lane: lane.index)
            edges[edge_id] = Edge(edge_id, edge.get("from", ""), edge.get("to", ""), tuple(edge_lanes))
    connections = []
    next_internal: dict[str, str] = {}
    for conn in root.iter("connection"):
        source, via = conn.get("from", ""), conn.get("via", "")
        from_lane = int(conn.get("fromLane", "0"))
        if source.startswith(":"):
            if via:
                next_internal[f"{source}_{from_lane}"] = via
            continue
        connections.append(
            Connection(
                from_edge=source,
                to_edge=conn.get("to", ""),
                from_lane=from_lane,
                to_lane=int(conn.get("toLane", "0")),
                via=via,
                tl=conn.get("tl", ""),
                link_index=int(conn.get("linkIndex", "-1")),
                direction=conn.get("dir", "s"),
            )
        )
    tls_ids = tuple(tl.get("id", "") for tl in root.iter("tlLogic"))
    fringe = frozenset(j.get("id", "") for j in root.iter("junction") if j.get("fringe") == "outer")
    if not edges:
        raise ValueError(f"{path}: the SUMO network has no edges")
    return SumoNet(lanes, edges, tuple(connections), next_internal, tls_ids, fringe)


def lane_directions(net: SumoNet, lane_ids: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Direction (rad, CCW from +x) of lane ``lane_ids[i]`` at SUMO position ``positions[i]``; NaN if unknown.

    Vectorized over all queries: the segments of every lane are laid end to end on one axis (lane by
    lane, a metre apart) and each query is located on it with one binary search.
    """
    lanes = list(net.lanes.values())
    segments = [np.diff(lane.shape, axis=0) for lane in lanes]
    seg_length = [np.linalg.norm(seg, axis=1) for seg in segments]
    geometry_length = np.array([lengths.sum() for lengths in seg_length])
    lane_base = np.concatenate([[0.0], np.cumsum(geometry_length + 1.0)[:-1]])
    seg_start = np.concatenate(
        [
            base + np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
            for base, lengths in zip(lane_base, seg_length, strict=True)
        ]
    )
    seg_angle = np.concatenate([np.arctan2(seg[:, 1], seg[:, 0]) for seg in segments])
    first_seg = np.concatenate([[0], np.cumsum([len(seg) for seg in segments])[:-1]])
    seg_count = np.array([len(seg) for seg in segments])
    sumo_length = np.array(
        [
            lane.length if lane.length > 0 else total
            for lane, total in zip(lanes, geometry_length, strict=True)
        ]
    )
    index = {lane.lane_id: k for k, lane in enumerate(lanes)}
    unique, inverse = np.unique(np.asarray(lane_ids), return_inverse=True)
    lane_of_unique = np.array([index.get(str(lane_id), -1) for lane_id in unique], dtype=np.int64)
    lane = lane_of_unique[inverse]
    known = lane >= 0
    k = np.where(known, lane, 0)
    along = np.clip(
        np.asarray(positions, dtype=np.float64) * geometry_length[k] / sumo_length[k], 0.0, geometry_length[k]
    )
    seg = np.searchsorted(seg_start, lane_base[k] + along, side="right") - 1
    seg = np.clip(seg, first_seg[k], first_seg[k] + seg_count[k] - 1)
    return np.where(known, seg_angle[seg], np.nan)
