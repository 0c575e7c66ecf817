"""The core data type: one driving scene as plain NumPy arrays in a global frame at 10 Hz.

Every source (highway-env, SUMO, WOMD, user arrays) produces a :class:`Scenario`; every consumer
(dataset, tokenizer, sampler, environment, metrics, rendering) reads one. Saving and loading live in
:mod:`trajeglish_env.scenario_io`.
"""

from __future__ import annotations

import hashlib
import itertools
from dataclasses import dataclass, field, fields, replace
from enum import IntEnum
from typing import NoReturn

import numpy as np


class AgentKind(IntEnum):
    """Class of a road user; each class has its own motion-token vocabulary."""

    VEHICLE = 0
    PEDESTRIAN = 1
    CYCLIST = 2


def agent_name(kind: int, track_id: int) -> str:
    """PettingZoo-style agent name, e.g. ``vehicle_2406`` (the env's names; warnings use them too)."""
    return f"{AgentKind(int(kind)).name.lower()}_{int(track_id)}"


class MapKind(IntEnum):
    """Type of one map polyline; the values follow WOMD's map feature types so conversion is exact."""

    LANE_UNDEFINED = 0
    LANE_FREEWAY = 1
    LANE_SURFACE_STREET = 2
    LANE_BIKE = 3
    ROAD_LINE_UNKNOWN = 4
    ROAD_LINE_BROKEN_SINGLE_WHITE = 5
    ROAD_LINE_SOLID_SINGLE_WHITE = 6
    ROAD_LINE_SOLID_DOUBLE_WHITE = 7
    ROAD_LINE_BROKEN_SINGLE_YELLOW = 8
    ROAD_LINE_BROKEN_DOUBLE_YELLOW = 9
    ROAD_LINE_SOLID_SINGLE_YELLOW = 10
    ROAD_LINE_SOLID_DOUBLE_YELLOW = 11
    ROAD_LINE_PASSING_DOUBLE_YELLOW = 12
    ROAD_EDGE_UNKNOWN = 13
    ROAD_EDGE_BOUNDARY = 14
    ROAD_EDGE_MEDIAN = 15
    STOP_SIGN = 16
    CROSSWALK = 17
    SPEED_BUMP = 18
    DRIVEWAY = 19


LANE_KINDS = frozenset(
    {MapKind.LANE_UNDEFINED, MapKind.LANE_FREEWAY, MapKind.LANE_SURFACE_STREET, MapKind.LANE_BIKE}
)
ROAD_LINE_KINDS = frozenset(MapKind(v) for v in range(4, 13))
ROAD_EDGE_KINDS = frozenset({MapKind.ROAD_EDGE_UNKNOWN, MapKind.ROAD_EDGE_BOUNDARY, MapKind.ROAD_EDGE_MEDIAN})


class SignalState(IntEnum):
    """Traffic-signal state of one controlled lane at one step (WOMD's TrafficSignalLaneState values)."""

    UNKNOWN = 0
    ARROW_STOP = 1
    ARROW_CAUTION = 2
    ARROW_GO = 3
    STOP = 4
    CAUTION = 5
    GO = 6
    FLASHING_STOP = 7
    FLASHING_CAUTION = 8


class ScenarioError(ValueError):
    """A Scenario (or a file holding one) is malformed; the message names the field and the problem."""


def _empty(shape: tuple[int, ...], dtype: type | np.dtype) -> np.ndarray:
    return np.zeros(shape, dtype=dtype)


@dataclass(frozen=True, eq=False)
class Scenario:
    """One driving scene: agent tracks and a map, in one global frame, sampled every ``dt`` seconds.

    Agents (N agents, T steps):
      ``xyh [N,T,3]`` float64 box-centre x, y (m) and heading (rad, CCW from +x);
      ``valid [N,T]`` bool; ``size [N,2]`` float64 (length, width in m); ``kind [N]`` int8 AgentKind;
      ``track_id [N]`` int64 unique ids; ``sdc`` index of the self-driving car (the default ego).
    Map (K polylines, P points in all), stored ragged:
      ``map_points [P,2]`` float64; ``map_offsets [K+1]`` int64 (polyline k is
      ``map_points[map_offsets[k]:map_offsets[k+1]]``); ``map_kind [K]`` int8 MapKind; ``map_id [K]`` int64.
    Traffic signals (L controlled lanes): ``signal_lane_id [L]`` int64 (a ``map_id``),
      ``signal_xy [L,2]`` stop point, ``signal_state [T,L]`` int8 SignalState.
    Metadata: ``dt`` (s), ``current_index`` (last step of given history), ``scenario_id``, ``source``,
      ``tracks_to_predict [M]`` int64 agent indices (may be empty).
    """

    xyh: np.ndarray
    valid: np.ndarray
    size: np.ndarray
    kind: np.ndarray
    track_id: np.ndarray
    sdc: int
    map_points: np.ndarray
    map_offsets: np.ndarray
    map_kind: np.ndarray
    map_id: np.ndarray
    scenario_id: str = ""
    source: str = "user"
    dt: float = 0.1
    current_index: int = 10
    tracks_to_predict: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    signal_lane_id: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    signal_xy: np.ndarray = field(default_factory=lambda: _empty((0, 2), np.float64))
    signal_state: np.ndarray | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(
        cls,
        xyh: np.ndarray,
        valid: np.ndarray,
        size: np.ndarray,
        kind: np.ndarray,
        *,
        track_id: np.ndarray | None = None,
        sdc: int = 0,
        polylines: list[np.ndarray] | None = None,
        polyline_kinds: list[int] | np.ndarray | None = None,
        polyline_ids: list[int] | np.ndarray | None = None,
        **metadata: object,
    ) -> Scenario:
        """Build and validate a Scenario from plain arrays and a list of polylines (how users bring data).
        The raw values are checked before they are cast (a kind of 256 or 1.7, a validity of 0.5, an sdc of
        1.5 or a polyline of [P, 3] points would otherwise turn silently into other values)."""
        sid = scenario_label(metadata.get("scenario_id", ""))
        line_kinds = [] if polyline_kinds is None else polyline_kinds
        tracks = np.arange(np.size(kind)) if track_id is None else np.ravel(track_id)
        lines = np.arange(np.size(line_kinds)) if polyline_ids is None else np.ravel(polyline_ids)
        _check_whole(sid, "kind", kind, 0, max(AgentKind), ("agent", "track_id", tracks))
        _check_whole(sid, "polyline_kinds", line_kinds, 0, max(MapKind), ("polyline", "map_id", lines))
        _check_whole(sid, "sdc", sdc, 0, None)
        raw_valid = np.asarray(valid)
        if raw_valid.dtype != bool and not np.isin(raw_valid, (0, 1)).all():
            raise ScenarioError(f"{sid}: field 'valid': expected booleans (or 0 / 1), got other values")
        for k, line in enumerate([] if polylines is None else polylines):
            if np.shape(line) != (2,) and (np.ndim(line) != 2 or np.shape(line)[1] != 2):
                raise ScenarioError(
                    f"{sid}: polylines[{k}]: expected [P, 2] points (x, y; a point: [2]); "
                    f"got {np.shape(line)}"
                )
        polylines = (
            [] if polylines is None else [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in polylines]
        )
        kinds = np.asarray([] if polyline_kinds is None else polyline_kinds, dtype=np.int8)
        if len(kinds) != len(polylines):
            raise ScenarioError(
                f"{sid}: field 'polyline_kinds': expected {len(polylines)} kinds (one per polyline), "
                f"got {len(kinds)}"
            )
        offsets = np.zeros(len(polylines) + 1, dtype=np.int64)
        offsets[1:] = np.cumsum([len(p) for p in polylines])
        points = np.concatenate(polylines) if polylines else _empty((0, 2), np.float64)
        ids = (
            np.arange(len(polylines), dtype=np.int64)
            if polyline_ids is None
            else np.asarray(polyline_ids, np.int64)
        )
        n = np.asarray(xyh).shape[0] if np.ndim(xyh) == 3 else 0
        scenario = cls(
            xyh=np.asarray(xyh, dtype=np.float64),
            valid=raw_valid.astype(bool),
            size=np.asarray(size, dtype=np.float64),
            kind=np.asarray(kind, dtype=np.int8),
            track_id=np.arange(n, dtype=np.int64)
            if track_id is None
            else np.asarray(track_id, dtype=np.int64),
            sdc=int(sdc),
            map_points=points,
            map_offsets=offsets,
            map_kind=kinds,
            map_id=ids,
            **metadata,  # type: ignore[arg-type]
        )
        scenario.validate()
        return scenario

    # ------------------------------------------------------------------ shape helpers
    @property
    def num_agents(self) -> int:
        return int(self.xyh.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.xyh.shape[1])

    @property
    def num_polylines(self) -> int:
        return int(self.map_kind.shape[0])

    def polyline(self, k: int) -> np.ndarray:
        """Points ``[n,2]`` of polyline ``k``."""
        return self.map_points[self.map_offsets[k] : self.map_offsets[k + 1]]

    def polylines(self, kinds: frozenset[MapKind] | None = None) -> list[np.ndarray]:
        """All polylines (optionally only those whose kind is in ``kinds``)."""
        return [
            self.polyline(k) for k in range(self.num_polylines) if kinds is None or self.map_kind[k] in kinds
        ]

    def speed(self) -> np.ndarray:
        """Finite-difference speed ``[N,T]`` in m/s (0 where either neighbour step is invalid)."""
        d = np.linalg.norm(np.diff(self.xyh[..., :2], axis=1), axis=-1) / self.dt
        ok = self.valid[:, 1:] & self.valid[:, :-1]
        out = np.zeros(self.valid.shape, dtype=np.float64)
        out[:, 1:] = np.where(ok, d, 0.0)
        out[:, 0] = out[:, 1] if self.num_steps > 1 else 0.0
        return out

    def agent_index(self, track_id: int) -> int:
        """Index of the agent with ``track_id``; a clear error if there is none."""
        hits = np.flatnonzero(self.track_id == track_id)
        if len(hits) == 0:
            raise KeyError(f"scenario {self.scenario_id!r}: no agent with track_id {track_id}")
        return int(hits[0])

    def with_agents(self, index: np.ndarray) -> Scenario:
        """A copy keeping only the agents at ``index`` (the sdc must be among them)."""
        index = np.asarray(index, dtype=np.int64)
        where = np.flatnonzero(index == self.sdc)
        if len(where) == 0:
            raise ScenarioError(f"with_agents: the sdc (agent {self.sdc}) must be kept")
        keep_predict = np.flatnonzero(np.isin(index, self.tracks_to_predict))
        return replace(
            self,
            xyh=self.xyh[index],
            valid=self.valid[index],
            size=self.size[index],
            kind=self.kind[index],
            track_id=self.track_id[index],
            sdc=int(where[0]),
            tracks_to_predict=keep_predict.astype(np.int64),
        )

    # ------------------------------------------------------------------ validation
    def validate(self) -> Scenario:
        """Check shapes, dtypes, finiteness and ranges of every field (vectorized, one pass); raise
        ScenarioError naming the scenario, the field, the agent (index and track id) or map point, the
        step and what was expected. Returns the scenario."""
        check = _Checker(self)
        n, t = check.agents()
        check.map_()
        check.metadata(n, t)
        check.signals(t)
        return self

    # ------------------------------------------------------------------ equality (exact, array-wise)
    def equals(self, other: Scenario) -> bool:
        """Exact equality of every field (arrays compared element-wise, dtypes included)."""
        for name in (f.name for f in fields(self)):
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (
                    isinstance(a, np.ndarray)
                    and isinstance(b, np.ndarray)
                    and a.dtype == b.dtype
                    and np.array_equal(a, b)
                ):
                    return False
            elif a != b:
                return False
        return True


# ---------------------------------------------------------------------------------------------- validation
_FLOAT, _INT, _BOOL = "f", "iu", "b"  # NumPy dtype kinds accepted per field


class _Checker:
    """The checks of :meth:`Scenario.validate`, grouped by part; every failure names the field."""

    def __init__(self, scenario: Scenario):
        self.sc = scenario
        self.sid = scenario_label(scenario.scenario_id)

    def fail(self, name: str, msg: str) -> NoReturn:
        """Raise the ScenarioError of field ``name``."""
        raise ScenarioError(f"{self.sid}: field '{name}': {msg}")

    def array(self, name: str, ndim: int, kinds: str, last: int | None = None) -> np.ndarray:
        """Field ``name`` as an array of ``ndim`` dimensions (last one ``last``) whose dtype kind is in
        ``kinds``."""
        arr = getattr(self.sc, name)
        if not isinstance(arr, np.ndarray):
            self.fail(name, f"expected a numpy array, got {type(arr).__name__}")
        if arr.ndim != ndim or (last is not None and arr.shape[-1] != last):
            want = f"{ndim}-d array" + (f" with last dimension {last}" if last is not None else "")
            self.fail(name, f"expected a {want}, got shape {arr.shape}")
        if arr.dtype.kind not in kinds:
            want = {_FLOAT: "a floating-point", _INT: "an integer", _BOOL: "a bool"}[kinds]
            self.fail(name, f"expected {want} dtype, got {arr.dtype}")
        return arr

    def rows(self, name: str, arr: np.ndarray, count: int, what: str) -> None:
        """``arr`` must have ``count`` rows (one per ``what``)."""
        if arr.shape[0] != count:
            self.fail(name, f"expected {count} entries (one per {what}), got {arr.shape[0]}")

    def track(self, i: int) -> str:
        """``track_id k`` of agent ``i`` (used once that field is known to be well-formed)."""
        return f"track_id {int(self.sc.track_id[i])}"

    def integer(self, name: str) -> int:
        """Scalar field ``name`` as an int (a Python or NumPy integer, not a bool)."""
        value = getattr(self.sc, name)
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            self.fail(name, f"expected an integer, got {value!r}")
        return int(value)

    # -------------------------------------------------------------- parts
    def agents(self) -> tuple[int, int]:
        """Agent arrays: shapes, dtypes, unique ids, finite valid states, positive sizes, known kinds."""
        xyh = self.array("xyh", 3, _FLOAT, 3)
        n, t = xyh.shape[:2]
        if t < 1:
            self.fail("xyh", "needs at least one timestep")
        track_id = self.array("track_id", 1, _INT)
        self.rows("track_id", track_id, n, "agent")
        ids, counts = np.unique(track_id, return_counts=True)
        if (counts > 1).any():
            self.fail(
                "track_id", f"ids must be unique; {int(ids[counts > 1][0])} appears {counts.max()} times"
            )
        valid = self.array("valid", 2, _BOOL)
        if valid.shape != (n, t):
            self.fail("valid", f"expected shape {(n, t)} (agents, steps of xyh), got {valid.shape}")
        bad = valid & ~np.isfinite(xyh).all(-1)
        if bad.any():
            i, step = (int(v) for v in np.argwhere(bad)[0])
            self.fail(
                "xyh",
                f"non-finite value at valid agent {i} step {step} ({self.track(i)}): expected finite "
                f"x, y, heading wherever valid is True, got {xyh[i, step].tolist()}",
            )
        size = self.array("size", 2, _FLOAT, 2)
        self.rows("size", size, n, "agent")
        bad_size = ~(np.isfinite(size) & (size > 0)).all(-1)
        if bad_size.any():
            i = int(np.flatnonzero(bad_size)[0])
            self.fail(
                "size",
                f"agent {i}: length and width must be finite and > 0 (m), got {size[i].tolist()} "
                f"({self.track(i)})",
            )
        kind = self.array("kind", 1, _INT)
        self.rows("kind", kind, n, "agent")
        bad_kind = (kind < 0) | (kind > max(AgentKind))
        if bad_kind.any():
            i = int(np.flatnonzero(bad_kind)[0])
            self.fail(
                "kind",
                f"values must be AgentKind 0..{int(max(AgentKind))}; agent {i} ({self.track(i)}) "
                f"has {int(kind[i])}",
            )
        sdc = self.integer("sdc")
        if n == 0 or not 0 <= sdc < n:
            self.fail("sdc", f"index {sdc} out of range for {n} agents")
        return n, t

    def map_(self) -> None:
        """Ragged map: offsets consistent with the points, finite points, known kinds."""
        points = self.array("map_points", 2, _FLOAT, 2)
        offsets = self.array("map_offsets", 1, _INT)
        k = offsets.shape[0] - 1
        if k < 0 or offsets[0] != 0 or offsets[-1] != len(points) or (np.diff(offsets) < 0).any():
            self.fail(
                "map_offsets",
                f"must start at 0, be non-decreasing and end at {len(points)} (number of points)",
            )
        map_kind = self.array("map_kind", 1, _INT)
        self.rows("map_kind", map_kind, k, "polyline")
        map_id = self.array("map_id", 1, _INT)
        self.rows("map_id", map_id, k, "polyline")
        bad_point = ~np.isfinite(points).all(-1)
        if bad_point.any():
            p = int(np.flatnonzero(bad_point)[0])
            line = int(np.searchsorted(offsets, p, side="right") - 1)
            self.fail(
                "map_points",
                f"point {p} (polyline {line}, map_id {int(map_id[line])}): expected finite x, y, "
                f"got {points[p].tolist()}",
            )
        bad_kind = (map_kind < 0) | (map_kind > max(MapKind))
        if bad_kind.any():
            line = int(np.flatnonzero(bad_kind)[0])
            self.fail(
                "map_kind",
                f"values must be MapKind 0..{int(max(MapKind))}; polyline {line} (map_id "
                f"{int(map_id[line])}) has {int(map_kind[line])}",
            )

    def metadata(self, n: int, t: int) -> None:
        """Sampling period, current step and the agents to predict."""
        dt = self.sc.dt
        if isinstance(dt, (bool, np.bool_)) or not isinstance(dt, (int, float, np.integer, np.floating)):
            self.fail("dt", f"must be a positive number of seconds, got {dt!r}")
        if not (np.isfinite(dt) and dt > 0):
            self.fail("dt", f"must be a positive number of seconds, got {dt}")
        current = self.integer("current_index")
        if not 0 <= current < t:
            self.fail("current_index", f"{current} out of range for {t} steps")
        ttp = self.array("tracks_to_predict", 1, _INT)
        if ((ttp < 0) | (ttp >= n)).any():
            self.fail("tracks_to_predict", f"agent indices must be in 0..{n - 1}, got {ttp.tolist()}")

    def signals(self, t: int) -> None:
        """Traffic signals: one stop point and one state per step for every controlled lane."""
        lanes = self.array("signal_lane_id", 1, _INT)
        sxy = self.array("signal_xy", 2, _FLOAT, 2)
        self.rows("signal_xy", sxy, lanes.shape[0], "signal")
        bad_xy = ~np.isfinite(sxy).all(-1)
        if bad_xy.any():
            j = int(np.flatnonzero(bad_xy)[0])
            self.fail(
                "signal_xy",
                f"signal {j} (lane {int(lanes[j])}): expected a finite stop point, got {sxy[j].tolist()}",
            )
        if self.sc.signal_state is None:
            if lanes.shape[0]:
                self.fail("signal_state", "signals are listed but their states are missing")
            return
        st = self.array("signal_state", 2, _INT)
        if st.shape != (t, lanes.shape[0]):
            self.fail(
                "signal_state", f"expected shape {(t, lanes.shape[0])} (steps, signals), got {st.shape}"
            )
        bad = (st < 0) | (st > max(SignalState))
        if bad.any():
            step, j = (int(v) for v in np.argwhere(bad)[0])
            self.fail(
                "signal_state",
                f"values must be SignalState 0..{int(max(SignalState))}; step {step}, signal {j} "
                f"(lane {int(lanes[j])}) has {int(st[step, j])}",
            )


def scene_kind(scene: Scenario) -> str:
    """The scene's kind for per-kind breakdowns: ``source/kind`` for generated scenes (their ids read
    ``source-kind-seed[-...]``, the kind possibly with dashes), else the source (WOMD: ``womd``)."""
    parts = scene.scenario_id.split("-")
    if scene.source in ("highway", "sumo") and parts[0] == scene.source:
        words = list(itertools.takewhile(lambda w: not w.isdigit(), parts[1:]))
        if words and len(words) < len(parts) - 1:
            return f"{scene.source}/{'-'.join(words)}"
    return scene.source


def scenario_label(scenario_id: object) -> str:
    """How error messages name a scene: ``scenario 'ID'``, or ``scenario <no id>`` for an empty id."""
    return f"scenario {scenario_id!r}" if scenario_id else "scenario <no id>"


def _check_whole(
    sid: str, field: str, values: object, low: int, high: int | None, entry: tuple | None = None
) -> None:
    """A ScenarioError unless every one of ``values`` is a whole number in ``[low, high]`` (no bools),
    naming the scene ``sid``, the field and the first offending entry (``entry``: what one is, the name of
    its id and the ids, e.g. ``("agent", "track_id", ids)``)."""
    array = np.asarray(values)
    if array.size == 0:
        return
    if array.dtype == bool or not np.issubdtype(array.dtype, np.number):
        raise ScenarioError(f"{sid}: field '{field}': expected whole numbers, got {array.dtype} values")
    bad = ~np.isfinite(array.astype(np.float64)) | (array != np.round(array)) | (array < low)
    if high is not None:
        bad |= array > high
    if bad.any():
        index = int(np.flatnonzero(bad.reshape(-1))[0])
        first = array.reshape(-1)[index].item()
        rng = f"in [{low}, {high}]" if high is not None else f">= {low}"
        at = ""
        if entry is not None:
            what, id_name, ids = entry
            at = f" at {what} {index}" + (f" ({id_name} {ids[index]})" if index < len(ids) else "")
        raise ScenarioError(f"{sid}: field '{field}': expected whole numbers {rng}, got {first!r}{at}")


def scenario_seed(seed: int, scenario_id: str) -> int:
    """The seed one scenario draws with in a run of seed ``seed``: a function of the two only, so a scene's
    rollouts or episode do not depend on which other scenes share the run, nor on their order."""
    digest = hashlib.sha256(f"{seed}/{scenario_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1
