"""One SUMO simulation of a random urban network, read back as dense agent tracks at 10 Hz.

SUMO runs as one subprocess writing floating-car data (CSV, vehicles and persons apart), traffic-light
states and collisions to files in a temporary directory; no TraCI round trips, so it is fast and safe
to run in parallel workers. SUMO's sub-lane model keeps lateral motion continuous.
"""

from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trajeglish_env.geometry import wrap_angle
from trajeglish_env.scenario import AgentKind
from trajeglish_env.sources.sumo_demand import AgentType, DemandConfig, write_demand
from trajeglish_env.sources.sumo_map import NetworkMap, build_network_map
from trajeglish_env.sources.sumo_net import SumoNet, build_network, lane_directions, parse_net
from trajeglish_env.sources.sumo_tools import run_tool

DT = 0.1


@dataclass(frozen=True)
class SimulationConfig:
    """SUMO settings of one simulation (the step is fixed at WOMD's 0.1 s)."""

    lateral_resolution_m: float = 0.8  # sub-lane width: continuous lateral motion, no lane-change jumps
    max_step_m: float = 4.0  # a move longer than this in one step is a teleport: the track is split there
    pedestrian_max_step_m: float = 1.5  # the same for pedestrians (SUMO sometimes hops them metres ahead)
    pedestrian_smoothing_steps: int = 3  # half-width of the moving average over pedestrian positions
    pedestrian_min_speed: float = 0.5  # below this (m/s) a pedestrian keeps its last heading
    min_turn_radius_m: float = 2.5  # vehicle and bicycle headings turn at most 1/this rad per metre
    max_lane_deviation_rad: float = 0.12  # on a normal lane, at most this far from the lane's direction
    map_spacing_m: float = 1.0
    demand: DemandConfig = field(default_factory=DemandConfig)


@dataclass(frozen=True)
class SumoRun:
    """Tracks of every agent of one simulation after warm-up (step 0 = end of warm-up), plus its map.

    ``xyh [N,T,3]`` box centres and headings (rad, CCW from +x), ``valid [N,T]``, ``on_junction [N,T]``
    (a vehicle or bicycle at least partly inside an intersection), ``size [N,2]``,
    ``kind [N]`` AgentKind, ``names [N]`` SUMO ids (a track split at a teleport gets ``#k`` suffixes);
    ``tls_states`` maps each traffic light to its SUMO state string per step; ``collisions`` lists
    ``(step, collider, victim)`` as SUMO reported them.
    """

    network_kind: str
    net_map: NetworkMap
    xyh: np.ndarray
    valid: np.ndarray
    on_junction: np.ndarray
    size: np.ndarray
    kind: np.ndarray
    names: tuple[str, ...]
    tls_states: dict[str, np.ndarray]
    collisions: tuple[tuple[int, str, str], ...]

    @property
    def num_steps(self) -> int:
        return int(self.valid.shape[1])


def _additional_file(tls_ids: tuple[str, ...], path: Path) -> None:
    events = "\n".join(f'<timedEvent type="SaveTLSStates" source="{t}" dest="tls.csv"/>' for t in tls_ids)
    path.write_text(f"<additional>\n{events}\n</additional>\n")


def _read_csv(path: Path, columns: tuple[str, ...]) -> np.ndarray:
    """Columns ``columns`` (by header name, without SUMO's ``vehicle_``/``person_`` prefix) of a SUMO CSV
    output as strings ``[R, len(columns)]``, keeping the rows that name an object (column 2)."""
    if not path.is_file():
        return np.zeros((0, len(columns)), dtype=str)
    text = path.read_text()
    header, _, body = text.partition("\n")
    names = [name.split("_", 1)[-1] for name in header.strip().split(";")]
    missing = [c for c in columns if c not in names]
    if missing:
        raise ValueError(f"{path.name}: SUMO output lacks columns {missing} (header: {header.strip()!r})")
    body = body.rstrip("\n")
    if not body:
        return np.zeros((0, len(columns)), dtype=str)
    fields = np.array(body.replace("\n", ";").split(";"))
    if len(fields) % len(names):
        raise ValueError(f"{path.name}: expected {len(names)} ';'-separated columns in every row")
    rows = fields.reshape(-1, len(names))
    rows = rows[rows[:, 1] != ""]
    return rows[:, [names.index(c) for c in columns]]


@dataclass(frozen=True)
class _Tracks:
    """Dense per-agent arrays as SUMO reports them (before splitting at teleports), steps from time 0."""

    xyh: np.ndarray  # [N,T,3] SUMO's reference point (a vehicle's front bumper) and heading (CCW from +x)
    speed: np.ndarray  # [N,T] speed along the lane (m/s; sideways sub-lane motion excluded)
    lane_heading: np.ndarray  # [N,T] direction of the normal lane under the whole vehicle; NaN elsewhere
    valid: np.ndarray  # [N,T]
    on_junction: np.ndarray  # [N,T] partly or wholly on a junction's internal lanes (or just inserted)
    size: np.ndarray  # [N,2]
    kind: np.ndarray  # [N]
    names: np.ndarray  # [N] SUMO ids


_FCD_COLUMNS = ("time", "id", "x", "y", "angle", "type", "speed", "pos", "lane")


def _read_fcd(paths: list[Path], num_steps: int, types: dict[str, AgentType], net: SumoNet) -> _Tracks:
    """Dense tracks from SUMO's FCD CSV files; SUMO angles (clockwise from north) become our headings."""
    rows = np.concatenate([_read_csv(path, _FCD_COLUMNS) for path in paths])
    if len(rows) == 0:
        raise ValueError("SUMO produced no floating-car data: the network stayed empty")
    time, ids, x, y, angle, type_ids, speed, pos, lane = rows.T
    names, first, agent = np.unique(ids, return_index=True, return_inverse=True)
    unknown = sorted(set(type_ids[first]) - set(types))
    if unknown:
        raise ValueError(
            f"SUMO floating-car data names vehicle types {unknown[:5]} that the demand did not define"
        )
    agent_types = [types[t] for t in type_ids[first]]
    size = np.array([[t.length, t.width] for t in agent_types], dtype=np.float64).reshape(-1, 2)
    kind = np.array([int(t.kind) for t in agent_types], dtype=np.int8)
    step = np.rint(time.astype(np.float64) / DT).astype(np.int64)
    heading = wrap_angle(0.5 * np.pi - np.radians(angle.astype(np.float64)))
    # A vehicle is in a junction while any part of it is: until its back has left the junction lanes.
    junction = np.char.startswith(lane, ":") | ((lane != "") & (pos.astype(np.float64) < size[agent, 0]))
    on_lane = (lane != "") & ~junction
    lane_heading = np.full(len(rows), np.nan)
    lane_heading[on_lane] = lane_directions(net, lane[on_lane], pos[on_lane].astype(np.float64))
    inside = (step >= 0) & (step < num_steps)
    a, s = agent[inside], step[inside]
    shape = (len(names), num_steps)
    xyh, valid = np.zeros((*shape, 3)), np.zeros(shape, dtype=bool)
    speeds, lane_headings, on_junction = np.zeros(shape), np.full(shape, np.nan), np.zeros(shape, dtype=bool)
    xyh[a, s] = np.stack([x.astype(np.float64), y.astype(np.float64), heading], -1)[inside]
    speeds[a, s] = speed[inside].astype(np.float64)
    lane_headings[a, s] = lane_heading[inside]
    valid[a, s] = True
    on_junction[a, s] = junction[inside]
    return _Tracks(xyh, speeds, lane_headings, valid, on_junction, size, kind, names)


def steer_limited_headings(
    xyh: np.ndarray, speed: np.ndarray, valid: np.ndarray, min_radius: float
) -> np.ndarray:
    """Vehicle headings ``[N,T]`` that turn at most 1/``min_radius`` rad per metre driven along the lane.

    SUMO's sub-lane model moves vehicles sideways even while they stand (e.g. squeezing into a turn
    lane at a red light) and then rotates their reported angle, sometimes by 45 degrees or more; a car
    cannot turn on the spot. Following SUMO's heading under this steering limit keeps every genuine
    turn (SUMO's lanes bend far more gently) and removes the rotation in place. Tracks must be
    contiguous (split first); ``speed`` is SUMO's speed along the lane.
    """
    out = xyh[..., 2].copy()
    limit = np.abs(speed) * DT / min_radius
    for t in range(1, valid.shape[1]):
        previous = out[:, t - 1]
        turn = np.clip(wrap_angle(xyh[:, t, 2] - previous), -limit[:, t], limit[:, t])
        out[:, t] = np.where(valid[:, t] & valid[:, t - 1], wrap_angle(previous + turn), xyh[:, t, 2])
    return out


def vehicle_boxes(
    front: np.ndarray,
    speed: np.ndarray,
    lane_heading: np.ndarray,
    valid: np.ndarray,
    length: np.ndarray,
    config: SimulationConfig,
) -> np.ndarray:
    """Box centres and headings ``[N,T,3]`` of vehicles from SUMO's front-bumper positions and angles.

    Where the whole vehicle is on a normal lane its heading keeps within ``max_lane_deviation_rad`` of
    the lane's direction (SUMO rotates vehicles that it slides sideways at low speed); elsewhere (in and
    just after junctions) it is SUMO's body angle. It is then
    steer-limited (:func:`steer_limited_headings`), and the centre lies half a length behind the front.
    """
    deviation = np.clip(
        wrap_angle(front[..., 2] - lane_heading),
        -config.max_lane_deviation_rad,
        config.max_lane_deviation_rad,
    )
    target = np.where(np.isfinite(lane_heading), wrap_angle(lane_heading + deviation), front[..., 2])
    heading = steer_limited_headings(
        np.concatenate([front[..., :2], target[..., None]], -1), speed, valid, config.min_turn_radius_m
    )
    back = 0.5 * np.asarray(length, dtype=np.float64)[:, None]
    centre = front[..., :2] - back[..., None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    return np.concatenate([centre, heading[..., None]], axis=-1)


def split_tracks(
    states: np.ndarray, valid: np.ndarray, max_step_m: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split tracks at gaps and teleports into separate agents.

    ``states [N,T,C]`` hold x, y first; ``max_step_m`` is one limit or one per agent. Returns (states,
    valid, source row of each new agent).
    """
    step_length = np.linalg.norm(np.diff(states[..., :2], axis=1), axis=-1)
    limit = np.broadcast_to(np.asarray(max_step_m, dtype=np.float64), (len(valid),))[:, None]
    continued = valid[:, 1:] & valid[:, :-1] & (step_length <= limit)
    starts = valid & ~np.concatenate([np.zeros((len(valid), 1), dtype=bool), continued], axis=1)
    segment = np.cumsum(starts, axis=1) - 1  # segment number of each valid step within its agent
    per_agent = starts.sum(axis=1)
    first_row = np.concatenate([[0], np.cumsum(per_agent)[:-1]]).astype(np.int64)
    rows = first_row[:, None] + segment
    source = np.repeat(np.arange(len(valid)), per_agent)
    out_states = np.zeros((int(per_agent.sum()), *states.shape[1:]), dtype=states.dtype)
    out_valid = np.zeros((int(per_agent.sum()), valid.shape[1]), dtype=bool)
    agent, step = np.nonzero(valid)
    out_states[rows[agent, step], step] = states[agent, step]
    out_valid[rows[agent, step], step] = True
    return out_states, out_valid, source


def _window_mean(values: np.ndarray, valid: np.ndarray, half: int) -> np.ndarray:
    """Centred moving average ``[N,T,D]`` over ``2*half+1`` steps, using valid steps only."""
    weights = valid[..., None].astype(np.float64)
    padded = np.pad(np.concatenate([values * weights, weights], axis=-1), ((0, 0), (half + 1, half), (0, 0)))
    total = np.cumsum(padded, axis=1)
    window = total[:, 2 * half + 1 :] - total[:, : -2 * half - 1]
    return window[..., :-1] / np.maximum(window[..., -1:], 1.0)


def smooth_pedestrians(xyh: np.ndarray, valid: np.ndarray, half: int, min_speed: float) -> np.ndarray:
    """Pedestrian tracks without SUMO's lane-transition hops: smoothed positions, headings from motion.

    SUMO's striping model moves a pedestrian sideways by up to a metre in one step where a sidewalk
    meets a walking area or crossing. A centred moving average spreads that hop over ``2*half+1``
    steps; the heading is the direction of the smoothed motion while faster than ``min_speed`` and is
    held while standing (SUMO's own angle before the first move). Tracks must be contiguous (split first).
    """
    xy = _window_mean(xyh[..., :2], valid, half)
    velocity = np.gradient(xy, DT, axis=1)
    moving = valid & (np.linalg.norm(velocity, axis=-1) > min_speed)
    steps = np.arange(valid.shape[1])
    last_move = np.maximum.accumulate(np.where(moving, steps, -1), axis=1)
    rows = np.arange(len(valid))[:, None]
    motion = np.arctan2(velocity[..., 1], velocity[..., 0])[rows, np.maximum(last_move, 0)]
    heading = np.where(last_move >= 0, motion, xyh[..., 2])
    out = np.concatenate([xy, heading[..., None]], axis=-1)
    return np.where(valid[..., None], out, 0.0)


def _read_tls(path: Path, begin: float, num_steps: int) -> dict[str, np.ndarray]:
    """Traffic-light state string per step for each light (columns time;id;programID;phase;state)."""
    rows = _read_csv(path, ("time", "id", "programID", "phase", "state"))
    step = np.rint((rows[:, 0].astype(np.float64) - begin) / DT).astype(np.int64)
    rows, step = rows[(step >= 0) & (step < num_steps)], step[(step >= 0) & (step < num_steps)]
    states: dict[str, np.ndarray] = {}
    for tls_id in np.unique(rows[:, 1]):
        mine = rows[:, 1] == tls_id
        column = np.full(num_steps, "", dtype=object)
        column[step[mine]] = rows[mine, 4]
        missing = np.flatnonzero(column == "")
        if len(missing):
            raise ValueError(f"SUMO traffic-light output: light {tls_id!r} has no state at step {missing[0]}")
        states[str(tls_id)] = column
    return states


def _read_collisions(path: Path, begin: float) -> tuple[tuple[int, str, str], ...]:
    if not path.is_file():
        return ()
    root = ET.parse(path).getroot()
    return tuple(
        (int(round((float(c.get("time", "0")) - begin) / DT)), c.get("collider", ""), c.get("victim", ""))
        for c in root.iter("collision")
    )


def simulate(kind: str, seed: int, warmup_s: float, duration_s: float, config: SimulationConfig) -> SumoRun:
    """Build a random ``kind`` network and demand from ``seed``, simulate, return the tracks after warm-up."""
    rng = np.random.default_rng(seed)
    num_steps = int(round((duration_s - warmup_s) / DT)) + 1  # kept after the warm-up
    total_steps = int(round(duration_s / DT)) + 1
    with tempfile.TemporaryDirectory(prefix="trajeglish-sumo-") as tmp:
        work = Path(tmp)
        net = parse_net(build_network(kind, rng, work))
        types = write_demand(net, rng, duration_s, work / "demand.rou.xml", config.demand)
        args = [
            "--net-file=scene.net.xml",
            "--route-files=demand.rou.xml",
            f"--end={duration_s + DT:.1f}",
            f"--step-length={DT}",
            f"--lateral-resolution={config.lateral_resolution_m}",
            f"--seed={int(rng.integers(0, 2**31 - 1))}",
            "--fcd-output=fcd.csv",
            "--person-fcd-output=person_fcd.csv",
            "--fcd-output.attributes=x,y,angle,type,speed,pos,lane",
            "--precision=3",
            "--collision-output=collisions.xml",
            "--collision.action=warn",
            "--collision.check-junctions",
            "--ignore-route-errors",
            "--no-step-log",
            "--no-warnings",
            "--xml-validation=never",
        ]
        if net.tls_ids:
            _additional_file(net.tls_ids, work / "tls.add.xml")
            args.append("--additional-files=tls.add.xml")
        run_tool("sumo", args, cwd=work)
        tracks = _read_fcd(
            [work / "fcd.csv", work / "person_fcd.csv"], total_steps, {t.type_id: t for t in types}, net
        )
        tls_states = _read_tls(work / "tls.csv", warmup_s, num_steps)
        collisions = _read_collisions(work / "collisions.xml", warmup_s)
    per_step = [tracks.speed, tracks.lane_heading, tracks.on_junction]
    states = np.concatenate([tracks.xyh, *[channel[..., None] for channel in per_step]], axis=-1)
    max_step = np.where(tracks.kind == AgentKind.PEDESTRIAN, config.pedestrian_max_step_m, config.max_step_m)
    states, valid, source = split_tracks(states, tracks.valid, max_step)
    xyh, kinds, size = np.ascontiguousarray(states[..., :3]), tracks.kind[source], tracks.size[source]
    walkers = kinds == AgentKind.PEDESTRIAN
    riders = ~walkers
    speed, lane_heading = states[..., 3], states[..., 4]
    xyh[riders] = vehicle_boxes(
        xyh[riders], speed[riders], lane_heading[riders], valid[riders], size[riders, 0], config
    )
    xyh[walkers] = smooth_pedestrians(
        xyh[walkers], valid[walkers], config.pedestrian_smoothing_steps, config.pedestrian_min_speed
    )
    # Drop the warm-up.
    first = total_steps - num_steps
    keep = valid[:, first:].any(axis=1)
    segment = np.arange(len(source)) - np.searchsorted(source, source)
    names = tuple(
        str(tracks.names[s]) if k == 0 else f"{tracks.names[s]}#{k}"
        for s, k, kept in zip(source, segment, keep, strict=True)
        if kept
    )
    return SumoRun(
        network_kind=kind,
        net_map=build_network_map(net, config.map_spacing_m),
        xyh=np.where(valid[keep, first:, None], xyh[keep, first:], 0.0),
        valid=valid[keep, first:],
        on_junction=states[keep, first:, 5] > 0.5,
        size=size[keep],
        kind=kinds[keep],
        names=names,
        tls_states=tls_states,
        collisions=collisions,
    )
