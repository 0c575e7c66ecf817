"""Convert a highway-env road network into Scenario map polylines (lane centres, road lines, road edges).

Each lane of ``road.network`` is sampled analytically (vectorized for highway-env's straight, sine and
circular lanes; a per-point fallback for other lane types) at about ``spacing`` metres, cropped to a
region of interest, and converted to WOMD-style map features:

- the lane's centre line -> ``lane_kind`` (LANE_FREEWAY or LANE_SURFACE_STREET);
- each painted side -> a road line: ``LineType.STRIPED`` -> ROAD_LINE_BROKEN_SINGLE_WHITE,
  ``CONTINUOUS``/``CONTINUOUS_LINE`` -> ROAD_LINE_SOLID_SINGLE_WHITE, ``NONE`` -> nothing (highway-env
  paints a boundary shared by two lanes on one of them only, so shared lines are not duplicated);
- road edges (ROAD_EDGE_BOUNDARY): the parts of a continuous lane side where no other lane lies just
  beyond it. The test is geometric (a probe point ``edge_probe`` metres outside the side must not lie
  on any lane), so kerbs stop where an entry or exit lane joins a roundabout ring, a splitter island
  between diverging entry/exit lanes is bounded, and the open inner box of an intersection (crossed by
  lanes whose sides carry no continuous line) gets no edge. Edges sit on the painted line (no shoulder).

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

_LINE_KIND = {
    LineType.STRIPED: MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE,
    LineType.CONTINUOUS: MapKind.ROAD_LINE_SOLID_SINGLE_WHITE,
    LineType.CONTINUOUS_LINE: MapKind.ROAD_LINE_SOLID_SINGLE_WHITE,
}
_CONTINUOUS = frozenset({LineType.CONTINUOUS, LineType.CONTINUOUS_LINE})


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


def _on_any_lane(lanes: list[AbstractLane], points: np.ndarray, skip: int) -> np.ndarray:
    """Mask ``[n]`` of points lying on some lane other than ``lanes[skip]`` (within its width and length)."""
    covered = np.zeros(len(points), dtype=bool)
    for k, lane in enumerate(lanes):
        if k == skip:
            continue
        s, lat = lane_local(lane, points)
        covered |= (np.abs(lat) <= 0.5 * float(lane.width_at(0.0))) & (s >= 0.0) & (s <= lane.length)
    return covered


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
        out.polylines.append(resample_polyline(points[start:end] * mirror, spacing))
        out.kinds.append(int(kind))


def network_polylines(
    network: RoadNetwork,
    lane_kind: MapKind,
    region: tuple[np.ndarray, np.ndarray],
    spacing: float = 0.5,
    edge_probe: float = 0.5,
    mirror_y: bool = True,
) -> MapPolylines:
    """Lane centres, road lines and road edges of ``network`` inside ``region`` (low, high corners).

    ``region`` is given in the Scenario frame; points are sampled every ``spacing`` metres at most.
    """
    if not spacing > 0:
        raise ValueError(f"map spacing must be > 0 metres, got {spacing}")
    mirror = np.array([1.0, -1.0 if mirror_y else 1.0])
    low, high = (np.asarray(c, dtype=np.float64) for c in region)
    lanes = network.lanes_list()
    out = MapPolylines([], [])
    lines = MapPolylines([], [])
    edges = MapPolylines([], [])
    seen: set[tuple[int, ...]] = set()
    for k, lane in enumerate(lanes):
        length = float(lane.length)
        s = np.linspace(0.0, length, max(int(np.ceil(length / (0.5 * spacing))), 1) + 1)
        half = 0.5 * float(lane.width_at(0.0))
        centre = lane_points(lane, s, 0.0)
        inside = np.all((centre * mirror >= low) & (centre * mirror <= high), axis=1)
        if inside.sum() < 2:
            continue
        _emit(out, centre, inside, lane_kind, spacing, mirror)
        for side, line_type in enumerate(lane.line_types or ()):
            if line_type not in _LINE_KIND:
                continue
            sign = 2.0 * side - 1.0  # side 0 lies at lateral -width/2, side 1 at +width/2
            boundary = lane_points(lane, s, sign * half)
            _emit(lines, boundary, inside, _LINE_KIND[line_type], spacing, mirror, seen)
            if line_type in _CONTINUOUS:
                probe = lane_points(lane, s, sign * (half + edge_probe))
                is_edge = inside & ~_on_any_lane(lanes, probe, skip=k)
                _emit(edges, boundary, is_edge, MapKind.ROAD_EDGE_BOUNDARY, spacing, mirror, seen)
    out.polylines.extend(lines.polylines + edges.polylines)
    out.kinds.extend(lines.kinds + edges.kinds)
    return out
