"""Convert a highway-env road network into Scenario map polylines (lane centres, road lines, road edges).

Each lane of ``road.network`` is sampled analytically (vectorized for highway-env's straight, sine and
circular lanes; a per-point fallback for other lane types) at about ``spacing`` metres, cropped to a
region of interest, and converted to WOMD-style map features:

- the lane's centre line -> ``lane_kind`` (LANE_FREEWAY or LANE_SURFACE_STREET);
- each painted side -> a road line: ``LineType.STRIPED`` -> ROAD_LINE_BROKEN_SINGLE_WHITE,
  ``CONTINUOUS``/``CONTINUOUS_LINE`` -> ROAD_LINE_SOLID_SINGLE_WHITE, ``NONE`` -> nothing (highway-env
  paints a boundary shared by two lanes on one of them only, so shared lines are not duplicated);
- road edges (ROAD_EDGE_BOUNDARY): the parts of a painted lane side (continuous or striped) where no
  other lane lies just beyond it. The test is geometric (a probe point ``edge_probe`` metres outside
  the side must not lie on any lane), so kerbs stop where an entry or exit lane joins a roundabout
  ring or a highway exit ramp leaves, the splitter island between diverging entry/exit lanes and the
  gore of an exit ramp (whose sides highway-env paints striped) are bounded, and the inner box of an
  intersection gets no edge (its turning lanes' unpainted sides are never edges: in highway-env an
  unpainted side is either painted by the neighbouring lane or lies inside a junction). Edges sit on
  the painted line (no shoulder) and are oriented with the road on their left (counter-clockwise
  around the drivable area, the convention of the WOSAC off-road metric). With ``kerb_radius`` the
  corner where one edge hands over to the next is rounded (:mod:`trajeglish_env.sources.kerb_corners`).

Geometry is computed in highway-env's native frame; the caller passes ``mirror_y`` to express it in the
Scenario frame (see :mod:`trajeglish_env.sources.highway`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, SineLane, StraightLane
from highway_env.road.road import RoadNetwork

from trajeglish_env.geometry import resample_polyline
from trajeglish_env.scenario import MapKind
from trajeglish_env.sources.kerb_corners import round_kerb_corners

_LINE_KIND = {
    LineType.STRIPED: MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE,
    LineType.CONTINUOUS: MapKind.ROAD_LINE_SOLID_SINGLE_WHITE,
    LineType.CONTINUOUS_LINE: MapKind.ROAD_LINE_SOLID_SINGLE_WHITE,
}


@dataclass(frozen=True)
class MapPolylines:
    """Map features as a list of polylines ``[n_k, 2]`` with one MapKind each (Scenario frame)."""

    polylines: list[np.ndarray]
    kinds: list[int]


def lane_points(lane: AbstractLane, longitudinal: np.ndarray, lateral: float) -> np.ndarray:
    """World points ``[n, 2]`` of ``lane`` at longitudinal coordinates ``[n]`` and one lateral offset."""
    s = np.asarray(longitudinal, dtype=np.float64)
    if isinstance(lane, SineLane):
        lat = lateral + lane.amplitude * np.sin(lane.pulsation * s + lane.phase)
        return lane.start + s[:, None] * lane.direction + lat[:, None] * lane.direction_lateral
    if isinstance(lane, StraightLane):
        return lane.start + s[:, None] * lane.direction + lateral * lane.direction_lateral
    if isinstance(lane, CircularLane):
        phi = lane.direction * s / lane.radius + lane.start_phase
        radius = lane.radius - lateral * lane.direction
        return lane.center + radius * np.stack([np.cos(phi), np.sin(phi)], -1)
    return np.array([lane.position(float(v), lateral) for v in s], dtype=np.float64).reshape(-1, 2)


def lane_local(lane: AbstractLane, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lane coordinates (longitudinal ``[n]``, lateral ``[n]``) of world points ``[n, 2]``."""
    points = np.asarray(points, dtype=np.float64)
    if isinstance(lane, StraightLane):
        delta = points - lane.start
        s = delta @ lane.direction
        lat = delta @ lane.direction_lateral
        if isinstance(lane, SineLane):
            lat = lat - lane.amplitude * np.sin(lane.pulsation * s + lane.phase)
        return s, lat
    if isinstance(lane, CircularLane):
        delta = points - lane.center
        phi = np.arctan2(delta[:, 1], delta[:, 0])
        phi = lane.start_phase + (phi - lane.start_phase + np.pi) % (2 * np.pi) - np.pi
        s = lane.direction * (phi - lane.start_phase) * lane.radius
        lat = lane.direction * (lane.radius - np.linalg.norm(delta, axis=1))
        return s, lat
    coords = np.array([lane.local_coordinates(p) for p in points], dtype=np.float64).reshape(-1, 2)
    return coords[:, 0], coords[:, 1]


def _covered(lanes: list[AbstractLane], points: np.ndarray, owner: np.ndarray, inset: float) -> np.ndarray:
    """Mask ``[n]`` of points lying on some lane other than their owner ``lanes[owner[i]]``: within the
    lane's length and within its width narrowed by ``inset`` metres on each side (one pass per lane)."""
    covered = np.zeros(len(points), dtype=bool)
    for k, lane in enumerate(lanes):
        s, lat = lane_local(lane, points)
        on = (np.abs(lat) <= 0.5 * float(lane.width_at(0.0)) - inset) & (s >= 0.0) & (s <= lane.length)
        covered |= on & (owner != k)
    return covered


def _sample_in_region(
    lane: AbstractLane, low: np.ndarray, high: np.ndarray, spacing: float, mirror: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """Longitudinal samples ``[n]`` (every ``spacing / 2``) spanning the part of ``lane`` near the region,
    and the mask of those whose centre point lies inside it; None when the lane misses the region.

    A coarse 5 m pass finds the span first, so a 10 km highway lane costs what its cropped part costs.
    """
    length, coarse_step = float(lane.length), 5.0
    coarse = np.linspace(0.0, length, max(int(np.ceil(length / coarse_step)), 1) + 1)
    near = np.all(
        np.abs(lane_points(lane, coarse, 0.0) * mirror - (low + high) / 2) <= (high - low) / 2 + 5.0, 1
    )
    if not near.any():
        return None
    first, last = (
        coarse[near.argmax()] - coarse_step,
        coarse[len(near) - 1 - near[::-1].argmax()] + coarse_step,
    )
    first, last = max(first, 0.0), min(last, length)
    s = np.linspace(first, last, max(int(np.ceil((last - first) / (0.5 * spacing))), 1) + 1)
    centre = lane_points(lane, s, 0.0) * mirror
    inside = np.all((centre >= low) & (centre <= high), axis=1)
    return (s, inside) if inside.sum() >= 2 else None


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges ``[start, end)`` of the consecutive True runs of ``mask``."""
    padded = np.concatenate([[False], mask, [False]])
    changes = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return list(zip(changes[0::2].tolist(), changes[1::2].tolist(), strict=True))


def _emit(
    out: MapPolylines,
    points: np.ndarray,
    keep: np.ndarray,
    kind: MapKind,
    spacing: float,
    mirror: np.ndarray,
    seen: set[tuple[int, ...]] | None = None,
    reverse: bool = False,
) -> None:
    """Append each run of kept points (at least two) as a resampled polyline of ``kind``.

    With ``seen``, a polyline whose end points (either direction, 0.1 m grid) and kind were already
    emitted is skipped: two lanes painting the same shared line give one polyline.
    """
    for start, end in _runs(keep):
        if end - start < 2:
            continue
        if seen is not None:
            ends = sorted(tuple(np.round(points[i] * 10).astype(np.int64).tolist()) for i in (start, end - 1))
            key = (int(kind), *ends[0], *ends[1])
            if key in seen:
                continue
            seen.add(key)
        run = points[start:end] * mirror
        out.polylines.append(resample_polyline(run[::-1] if reverse else run, spacing))
        out.kinds.append(int(kind))


def network_polylines(
    network: RoadNetwork,
    lane_kind: MapKind,
    region: tuple[np.ndarray, np.ndarray],
    spacing: float = 0.5,
    edge_probe: float = 0.5,
    mirror_y: bool = True,
    kerb_radius: float = 0.0,
) -> MapPolylines:
    """Lane centres, road lines and road edges of ``network`` inside ``region`` (low, high corners).

    ``region`` is given in the Scenario frame; points are sampled every ``spacing`` metres at most. With
    ``kerb_radius`` > 0 the kerb corners where one edge hands over to the next are rounded
    (:func:`~trajeglish_env.sources.kerb_corners.round_kerb_corners`).
    """
    if not spacing > 0:
        raise ValueError(f"map spacing must be > 0 metres, got {spacing}")
    mirror = np.array([1.0, -1.0 if mirror_y else 1.0])
    low, high = (np.asarray(c, dtype=np.float64) for c in region)
    lanes = network.lanes_list()
    centres = MapPolylines([], [])
    lines = MapPolylines([], [])
    edges = MapPolylines([], [])
    seen: set[tuple[int, ...]] = set()
    # Painted sides: (lane, side, its boundary points, region mask); their edge tests run batched below.
    sides: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    probes: list[np.ndarray] = []
    for k, lane in enumerate(lanes):
        sampled = _sample_in_region(lane, low, high, spacing, mirror)
        if sampled is None:
            continue
        s, inside = sampled
        _emit(centres, lane_points(lane, s, 0.0), inside, lane_kind, spacing, mirror)
        half = 0.5 * float(lane.width_at(0.0))
        for side, line_type in enumerate(lane.line_types or ()):
            if line_type not in _LINE_KIND:
                continue
            sign = 2.0 * side - 1.0  # side 0 lies at lateral -width/2, side 1 at +width/2
            boundary = lane_points(lane, s, sign * half)
            _emit(lines, boundary, inside, _LINE_KIND[line_type], spacing, mirror, seen)
            sides.append((k, side, boundary, inside))
            probes.append(lane_points(lane, s, sign * (half + edge_probe)))
    if sides:
        owner = np.concatenate([np.full(len(b), k) for k, _, b, _ in sides])
        boundaries = np.concatenate([b for _, _, b, _ in sides])
        # An edge needs open ground just beyond the side, and must not itself cut into another lane
        # (where an entry lane meets a roundabout ring obliquely, its kerb would poke into the ring).
        open_side = ~_covered(lanes, np.concatenate(probes), owner, 0.0)
        open_side &= ~_covered(lanes, boundaries, owner, edge_probe)
        splits = np.cumsum([len(b) for _, _, b, _ in sides])[:-1]
        for (_, side, boundary, inside), is_open in zip(sides, np.split(open_side, splits), strict=True):
            # Along the lane, side 1 lies on the lane's left in highway-env's frame, so the road is on
            # the edge's right there and on its left once y is mirrored; orient every edge road-on-left.
            reverse = (side == 1) != mirror_y
            _emit(
                edges, boundary, inside & is_open, MapKind.ROAD_EDGE_BOUNDARY, spacing, mirror, seen, reverse
            )
    if kerb_radius > 0:
        edges = MapPolylines(round_kerb_corners(edges.polylines, kerb_radius, spacing), edges.kinds)
    return MapPolylines(
        centres.polylines + lines.polylines + edges.polylines, centres.kinds + lines.kinds + edges.kinds
    )
