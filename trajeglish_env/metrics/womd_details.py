"""Read the raw WOMD values the metrics need (z, box height, raw invalid states, object types, map z,
per-step stop points) as :class:`LogDetails` aligned with :func:`trajeglish_env.sources.womd.read_womd`.

Alignment follows the reader's rules: tracks without any valid state are dropped, map features keep
their order (features without geometry are skipped; polygons are closed by repeating their first point;
a stop sign is one point), signals are the union of the reported lanes sorted by lane id.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np
from google.protobuf.message import DecodeError, Message

from trajeglish_env.metrics.log_details import LogDetails
from trajeglish_env.sources.womd_proto import ScenarioProto
from trajeglish_env.sources.womd_tfrecord import WomdFormatError, read_tfrecord

__all__ = ["parse_womd_details", "read_womd_details"]

_POLYLINE_FEATURES = ("lane", "road_line", "road_edge")
_POLYGON_FEATURES = ("crosswalk", "speed_bump", "driveway")


def _map_z(features: list[Message]) -> np.ndarray:
    """z of every map point, in the order the reader lays out ``Scenario.map_points``."""
    zs: list[float] = []
    for feature in features:
        which = feature.WhichOneof("feature_data")
        if which is None:
            continue
        data = getattr(feature, which)
        if which in _POLYLINE_FEATURES:
            z = [p.z for p in data.polyline]
        elif which in _POLYGON_FEATURES:
            z = [p.z for p in data.polygon]
            z = z + z[:1]
        else:  # stop_sign
            z = [data.position.z] if data.HasField("position") else []
        zs.extend(z)
    return np.array(zs, dtype=np.float64)


def _signal_stops(proto: Message, steps: int) -> np.ndarray:
    """Stop point ``[T, L, 2]`` of each reported lane (sorted by id) at each step, (0, 0) if absent."""
    rows = [
        (g, s.lane, s.stop_point.x, s.stop_point.y)
        for g, dynamic in enumerate(proto.dynamic_map_states[:steps])
        for s in dynamic.lane_states
    ]
    lanes = np.unique(np.array([r[1] for r in rows], dtype=np.int64))
    out = np.zeros((steps, len(lanes), 2), dtype=np.float64)
    if rows:
        g = np.array([r[0] for r in rows], dtype=np.int64)
        column = np.searchsorted(lanes, np.array([r[1] for r in rows], dtype=np.int64))
        out[g, column] = np.array([r[2:] for r in rows], dtype=np.float64)
    return out


def parse_womd_details(data: bytes, *, origin: str = "") -> LogDetails:
    """:class:`LogDetails` of one serialized WOMD ``Scenario`` proto."""
    where = f"{origin}: " if origin else ""
    try:
        proto = ScenarioProto.FromString(data)
    except DecodeError as exc:
        raise WomdFormatError(f"{where}not a valid WOMD Scenario protobuf: {exc}") from exc
    tracks = proto.tracks
    steps = {len(track.states) for track in tracks}
    if len(tracks) == 0 or len(steps) != 1 or 0 in steps:
        raise WomdFormatError(f"{where}tracks must all have the same, non-zero number of states")
    t = steps.pop()
    current = int(proto.current_time_index)
    if not 0 <= current < t:
        raise WomdFormatError(f"{where}current_time_index {current} out of range for {t} steps")
    states = np.array(
        [
            (s.center_x, s.center_y, s.center_z, s.heading, s.length, s.width, s.height, s.valid)
            for track in tracks
            for s in track.states
        ],
        dtype=np.float64,
    ).reshape(len(tracks), t, 8)
    keep = np.flatnonzero((states[..., 7] > 0).any(axis=1))
    states = states[keep]
    return LogDetails(
        track_id=np.array([tracks[int(i)].id for i in keep], dtype=np.int64),
        xyz=states[..., :3].copy(),
        heading=states[..., 3].copy(),
        box=states[:, current, 4:7].copy(),
        object_type=np.array([tracks[int(i)].object_type for i in keep], dtype=np.int64),
        map_z=_map_z(list(proto.map_features)),
        signal_stop=_signal_stops(proto, t),
    )


def read_womd_details(path: str | os.PathLike[str]) -> Iterator[LogDetails]:
    """Yield the :class:`LogDetails` of every scene of a WOMD TFRecord file, in file order."""
    for index, data in read_tfrecord(path):
        yield parse_womd_details(data, origin=f"{path}: record {index}")
