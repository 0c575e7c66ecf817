"""Reader of the Waymo Open Motion Dataset (WOMD): TFRecord files of ``Scenario`` protos -> Scenarios.

No TensorFlow and no protoc: records are unframed by :mod:`womd_tfrecord` and parsed with the schema
subset of :mod:`womd_proto`. Conversion choices (all explicit here):

- agents: ``xyh`` = (center_x, center_y, heading), zeroed where a state is invalid; ``size`` = the
  (length, width) of the valid state nearest to ``current_index`` (earlier wins a tie), because the
  simulator keeps one box per agent. Tracks without any valid state carry nothing and are dropped
  (``sdc`` and ``tracks_to_predict`` are re-indexed); a dropped sdc is an error.
- agent kinds: see :data:`OBJECT_TYPE_TO_KIND` (TYPE_OTHER and TYPE_UNSET become VEHICLE).
- map: lane centres, road lines and road edges keep their polylines; crosswalk, speed-bump and
  driveway polygons become closed polylines (first point repeated); a stop sign is a one-point polyline.
  MapKind values are WOMD's per-feature enums laid end to end (lane type + 0, road-line type + 4,
  road-edge type + 13), as in Waymax. Features without geometry or of an unknown type are skipped.
- traffic signals: the union of the lanes seen over all steps, sorted by lane id; the stop point is
  the lane's first reported one; steps where a lane is not reported are UNKNOWN (SignalState values
  equal WOMD's TrafficSignalLaneState.State values).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from google.protobuf.message import DecodeError, Message

from trajeglish_env.scenario import AgentKind, MapKind, Scenario, ScenarioError, SignalState
from trajeglish_env.scenario_io import SUFFIX
from trajeglish_env.sources.womd_proto import ScenarioProto
from trajeglish_env.sources.womd_tfrecord import TFRecordFramingError, WomdFormatError, read_tfrecord

__all__ = [
    "OBJECT_TYPE_TO_KIND",
    "TFRecordFramingError",
    "WomdFormatError",
    "good_records",
    "no_records_error",
    "output_name",
    "parse_scenario",
    "read_good_records",
    "read_tfrecord",
    "read_womd",
    "read_womd_at",
]

# WOMD Track.ObjectType -> AgentKind. TYPE_OTHER (4) and TYPE_UNSET (0) are rare; they are moving road
# users that must stay in the scene as obstacles, and the vehicle vocabulary is the most general one.
OBJECT_TYPE_TO_KIND: dict[int, AgentKind] = {
    0: AgentKind.VEHICLE,  # TYPE_UNSET
    1: AgentKind.VEHICLE,  # TYPE_VEHICLE
    2: AgentKind.PEDESTRIAN,  # TYPE_PEDESTRIAN
    3: AgentKind.CYCLIST,  # TYPE_CYCLIST
    4: AgentKind.VEHICLE,  # TYPE_OTHER
}
_KIND_LOOKUP = np.array([OBJECT_TYPE_TO_KIND[t] for t in range(len(OBJECT_TYPE_TO_KIND))], dtype=np.int8)

# MapFeature oneof name -> (first MapKind, number of type values) for the typed polyline features.
_TYPED_POLYLINES = {
    "lane": (MapKind.LANE_UNDEFINED, 4),
    "road_line": (MapKind.ROAD_LINE_UNKNOWN, 9),
    "road_edge": (MapKind.ROAD_EDGE_UNKNOWN, 3),
}
_POLYGONS = {"crosswalk": MapKind.CROSSWALK, "speed_bump": MapKind.SPEED_BUMP, "driveway": MapKind.DRIVEWAY}
_DEFAULT_DT = 0.1  # WOMD's sampling period, used when a record has fewer than two timestamps
_DT_TOLERANCE = 0.2  # a step may deviate from the mean period by this fraction before it is an error


def parse_scenario(data: bytes, *, origin: str = "") -> Scenario:
    """Convert one serialized WOMD ``Scenario`` proto to a validated :class:`Scenario`.

    ``origin`` (e.g. ``"file.tfrecord: record 3"``) prefixes every error message.
    """
    where = f"{origin}: " if origin else ""
    try:
        proto = ScenarioProto.FromString(data)
    except DecodeError as exc:
        raise WomdFormatError(f"{where}not a valid WOMD Scenario protobuf: {exc}") from exc
    try:
        return _convert(proto, where)
    except ScenarioError as exc:
        raise WomdFormatError(f"{where}{exc}") from exc


def read_womd(path: str | os.PathLike[str]) -> Iterator[Scenario]:
    """Yield every scene of a WOMD TFRecord file, in file order; a file without records is an error."""
    empty = True
    for index, data in read_tfrecord(path):
        empty = False
        yield parse_scenario(data, origin=f"{path}: record {index}")
    if empty:
        raise no_records_error(path)


def read_womd_at(path: str | os.PathLike[str], index: int) -> Scenario:
    """The ``index``-th scene (0-based, in file order) of a WOMD TFRecord file; only that record is parsed.
    An index past the file's records is a :class:`WomdFormatError` naming the file and its record count."""
    if index < 0:
        raise WomdFormatError(f"{path}: scenario index {index} is negative")
    count = 0
    for count, (number, data) in enumerate(read_tfrecord(path), start=1):
        if count - 1 == index:
            return parse_scenario(data, origin=f"{path}: record {number}")
    if count == 0:
        raise no_records_error(path)
    raise WomdFormatError(f"{path} holds {count} scenario(s); index {index} is out of range")


def no_records_error(path: str | os.PathLike[str]) -> WomdFormatError:
    """The error of a TFRecord file that holds no record."""
    return WomdFormatError(f"{path}: no records (empty file: it holds no scenario)")


def output_name(path: str | os.PathLike[str]) -> str:
    """Output shard name of a WOMD file, unique per input name.

    ``training.tfrecord-00001-of-01000`` -> ``training-00001-of-01000.scn.npz`` (``Path.stem`` would
    collapse every shard of a split to ``training``).
    """
    name = Path(path).name
    return name.replace(".tfrecord", "", 1) + SUFFIX


def good_records(
    path: str | os.PathLike[str], bad_records: list[TFRecordFramingError] | None = None
) -> tuple[list[tuple[int, bytes]], TFRecordFramingError | None]:
    """The good records ``(index, bytes)`` of a TFRecord file and the framing error of its bad tail (None
    if the file is intact). A file whose first record is already bad is an error. With a ``bad_records``
    list, a corrupt record whose framing is intact (data checksum wrong) is skipped and appended to it
    instead of ending the file (see :func:`read_tfrecord`); a file of nothing but such records is an error."""
    records: list[tuple[int, bytes]] = []
    skipped = [] if bad_records is None else bad_records
    try:
        for index, data in read_tfrecord(path, bad_records=bad_records):
            records.append((index, data))
    except TFRecordFramingError as exc:
        if not records:
            raise
        return records, exc
    if not records and skipped:
        raise skipped[0]
    return records, None


def read_good_records(
    path: str | os.PathLike[str], bad_records: list[TFRecordFramingError] | None = None
) -> tuple[list[Scenario], TFRecordFramingError | None]:
    """The scenes of a TFRecord file's good records, and the framing error of its bad tail (None if the
    file is intact). A file whose first record is already bad, or that holds no record, is an error.
    ``bad_records``: as in :func:`good_records`."""
    records, tail = good_records(path, bad_records)
    if not records:
        raise no_records_error(path)
    return [parse_scenario(data, origin=f"{path}: record {index}") for index, data in records], tail


# ---------------------------------------------------------------------------------------------- conversion
def _convert(proto: Message, where: str) -> Scenario:
    """Proto -> Scenario (see the module docstring for the choices)."""
    tracks = proto.tracks
    n = len(tracks)
    if n == 0:
        raise WomdFormatError(f"{where}scenario {proto.scenario_id!r} has no tracks")
    t = _steps(tracks, where)
    sdc = int(proto.sdc_track_index)
    if not 0 <= sdc < n:
        raise WomdFormatError(f"{where}sdc_track_index {sdc} out of range for {n} tracks")
    current = int(proto.current_time_index)
    if not 0 <= current < t:
        raise WomdFormatError(f"{where}current_time_index {current} out of range for {t} steps")
    predict = np.array([r.track_index for r in proto.tracks_to_predict], dtype=np.int64)
    if ((predict < 0) | (predict >= n)).any():
        raise WomdFormatError(f"{where}tracks_to_predict {predict.tolist()} out of range for {n} tracks")

    states = np.array(
        [
            (s.center_x, s.center_y, s.heading, s.length, s.width, s.valid)
            for track in tracks
            for s in track.states
        ],
        dtype=np.float64,
    ).reshape(n, t, 6)
    valid = states[..., 5] > 0
    track_id = np.array([track.id for track in tracks], dtype=np.int64)
    object_type = np.array([track.object_type for track in tracks], dtype=np.int64)
    bad_type = (object_type < 0) | (object_type >= len(_KIND_LOOKUP))
    if bad_type.any():
        i = int(np.flatnonzero(bad_type)[0])
        raise WomdFormatError(f"{where}track {track_id[i]}: unknown object_type {object_type[i]}")
    xyh = np.where(valid[..., None], states[..., :3], 0.0)
    size = _agent_size(states[..., 3:5], valid, current, track_id, where)

    keep = np.flatnonzero(valid.any(axis=1))
    if not valid[sdc].any():
        raise WomdFormatError(f"{where}the sdc (track {track_id[sdc]}) has no valid state")
    new_index = np.full(n, -1, dtype=np.int64)
    new_index[keep] = np.arange(len(keep))
    predict = new_index[predict]

    points, offsets, map_kind, map_id = _map_features(proto.map_features, where)
    signal_lane_id, signal_xy, signal_state = _traffic_signals(proto.dynamic_map_states, t, where)
    return Scenario(
        xyh=xyh[keep],
        valid=valid[keep],
        size=size[keep],
        kind=_KIND_LOOKUP[object_type[keep]],
        track_id=track_id[keep],
        sdc=int(new_index[sdc]),
        map_points=points,
        map_offsets=offsets,
        map_kind=map_kind,
        map_id=map_id,
        scenario_id=str(proto.scenario_id),
        source="womd",
        dt=_sampling_period(np.asarray(proto.timestamps_seconds, dtype=np.float64), where),
        current_index=current,
        tracks_to_predict=predict[predict >= 0],
        signal_lane_id=signal_lane_id,
        signal_xy=signal_xy,
        signal_state=signal_state,
    ).validate()


def _steps(tracks: Sequence[Message], where: str) -> int:
    """The number of states every track has; a ragged or empty track is an error naming the odd tracks."""
    counts = np.array([len(track.states) for track in tracks], dtype=np.int64)
    values, seen = np.unique(counts, return_counts=True)
    common = int(values[np.lexsort((values, seen))[-1]])  # the most frequent count (the larger on a tie)
    if len(values) == 1 and common > 0:
        return common
    odd = np.flatnonzero(counts != common) if common > 0 else np.flatnonzero(counts == 0)
    named = ", ".join(f"track {tracks[i].id} (index {i}) has {counts[i]} states" for i in odd[:5])
    more = f" and {len(odd) - 5} more" if len(odd) > 5 else ""
    others = f"the others have {common}" if common > 0 else "a track needs at least one state"
    raise WomdFormatError(
        f"{where}tracks must all have the same, non-zero number of states: {named}{more}; {others}"
    )


def _agent_size(
    dims: np.ndarray, valid: np.ndarray, current: int, track_id: np.ndarray, where: str
) -> np.ndarray:
    """Per-agent (length, width) ``[N,2]``: the valid, positive box nearest in time to ``current``."""
    usable = valid & (dims > 0).all(axis=-1)
    no_box = valid.any(axis=1) & ~usable.any(axis=1)
    if no_box.any():
        i = int(np.flatnonzero(no_box)[0])
        raise WomdFormatError(f"{where}track {track_id[i]}: no valid state has a positive length and width")
    distance = np.abs(np.arange(valid.shape[1]) - current)
    best = np.argmin(np.where(usable, distance[None, :], np.iinfo(np.int64).max), axis=1)
    size = dims[np.arange(len(dims)), best]
    return np.where(usable.any(axis=1)[:, None], size, 1.0)  # tracks with no valid state are dropped later


def _sampling_period(timestamps: np.ndarray, where: str) -> float:
    """Mean step of the timestamps rounded to milliseconds; an error if the steps are far from uniform."""
    if len(timestamps) < 2:
        return _DEFAULT_DT
    steps = np.diff(timestamps)
    dt = round(float((timestamps[-1] - timestamps[0]) / (len(timestamps) - 1)), 3)
    off = np.abs(steps - dt) > _DT_TOLERANCE * dt
    if dt <= 0 or off.any():
        i = int(np.flatnonzero(off)[0]) if off.any() else 0
        raise WomdFormatError(
            f"{where}timestamps_seconds are not uniformly increasing (step {i}: {steps[i]:.4f} s)"
        )
    return dt


def _map_features(
    features: Sequence[Message], where: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ragged map arrays (points, offsets, kinds, ids) from the MapFeature list."""
    coords: list[tuple[float, float]] = []
    counts: list[int] = []
    kinds: list[int] = []
    ids: list[int] = []
    for feature in features:
        which = feature.WhichOneof("feature_data")
        if which is None:
            continue
        data = getattr(feature, which)
        if which in _TYPED_POLYLINES:
            first, count = _TYPED_POLYLINES[which]
            if not 0 <= data.type < count:
                raise WomdFormatError(f"{where}map feature {feature.id} ({which}): unknown type {data.type}")
            kind = first + data.type
            xy = [(p.x, p.y) for p in data.polyline]
        elif which in _POLYGONS:
            kind = _POLYGONS[which]
            xy = [(p.x, p.y) for p in data.polygon]
            xy = xy + xy[:1]
        else:  # stop_sign
            kind = MapKind.STOP_SIGN
            xy = [(data.position.x, data.position.y)] if data.HasField("position") else []
        if not xy:
            continue
        coords.extend(xy)
        counts.append(len(xy))
        kinds.append(kind)
        ids.append(feature.id)
    offsets = np.zeros(len(counts) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(counts, dtype=np.int64)
    points = np.array(coords, dtype=np.float64).reshape(-1, 2)
    return points, offsets, np.array(kinds, dtype=np.int8), np.array(ids, dtype=np.int64)


def _traffic_signals(
    dynamic_states: Sequence[Message], steps: int, where: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lane ids [L], stop points [L,2], states [T,L]) for the signal-controlled lanes seen in the scene."""
    rows = [
        (step, s.lane, s.state, s.stop_point.x, s.stop_point.y)
        for step, dynamic in enumerate(dynamic_states[:steps])
        for s in dynamic.lane_states
    ]
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float64), np.zeros((steps, 0), np.int8)
    step = np.array([r[0] for r in rows], dtype=np.int64)
    lane = np.array([r[1] for r in rows], dtype=np.int64)
    state = np.array([r[2] for r in rows], dtype=np.int64)
    stop_xy = np.array([r[3:] for r in rows], dtype=np.float64)
    bad = (state < 0) | (state > max(SignalState))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise WomdFormatError(
            f"{where}step {step[i]}: traffic signal of lane {lane[i]} has unknown state {state[i]}"
        )
    lanes, first, column = np.unique(lane, return_index=True, return_inverse=True)
    table = np.zeros(
        (steps, len(lanes)), dtype=np.int8
    )  # 0 = SignalState.UNKNOWN where a lane is not reported
    table[step, column] = state
    return lanes, stop_xy[first], table
