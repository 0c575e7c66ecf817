"""Scene source: traffic scenes simulated with highway-env, every vehicle driven by IDM/MOBIL.

highway-env's environment classes only build the road and the initial traffic (seeded through the
env's ``np_random``, which its road shares); the simulation is then stepped directly
(``road.act(); road.step(dt)``) with no observation, reward or rendering work. Every vehicle, the ego
included, is a :class:`SceneIDMVehicle` (highway-env's IDM longitudinal + MOBIL lane-change model, see
:mod:`trajeglish_env.sources.highway_kinds` for the kinds and their traffic).

Frames. highway-env draws its world with the y axis pointing down the screen, so in a standard
right-handed (y up) reading its traffic drives on the left. We mirror y (``y -> -y``,
``heading -> -heading``): the scene then looks exactly as highway-env renders it, keeps right-hand
traffic (roundabouts turn counter-clockwise) and motion still follows the heading. ``vehicle.position``
is the box centre (``RoadObject.polygon`` is centred on it), so positions are taken as they are.
Headings are highway-env's box headings; its kinematic bicycle model moves the box centre at a slip
angle ``asin(yaw_rate * length / 2 / speed)`` off the heading (a few degrees on a ring, more in
tight slow turns).

Rates. The simulation runs at ``substeps`` x 10 Hz and every ``substeps``-th state is recorded. The
default is 10 Hz (``substeps=1``): it needs no resampling, the controllers are stable at this rate
(highway-env's own "fast" variants use 5 Hz) and it is the cheapest choice.

Agents. Each vehicle object gets one track (ids in order of first appearance), valid on the steps it
is on the road: the intersection spawns and clears traffic every second as its env does, and a
vehicle that drives past the end of a lane with no successor leaves the road. Vehicles that never
come within ``agent_radius`` of the sdc are dropped. A crash involving the ego (or any kept vehicle,
by default) discards the try and retries with a seed derived from (seed, attempt).

Bit-identical: the scene is a pure function of (kind, seed, config).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

from trajeglish_env.geometry import wrap_angle
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.sources.generation import scene_seed
from trajeglish_env.sources.highway_kinds import (
    KIND_SPECS,
    KINDS,
    KindSpec,
    SceneIDMVehicle,
    as_scene_vehicle,
    base_env_config,
)
from trajeglish_env.sources.highway_map import network_polylines
from trajeglish_env.sources.highway_stops import (
    STOP_SUFFIX,
    StopEvent,
    choose_stopper,
    draw_stop_event,
    split_kind,
    start_stop,
    stop_id_suffix,
)

__all__ = [
    "EXTRA_KINDS",
    "KINDS",
    "HighwaySceneConfig",
    "SceneCrashError",
    "SceneIDMVehicle",
    "check_kind",
    "generate_scene",
    "generate_shard",
]

SOURCE = "highway"
# 2: rounded kerb corners (HighwaySceneConfig.kerb_radius); 3: no lane changes in two-way scenes
GENERATOR_VERSION = 3
# Kinds accepted by ``--kinds`` but not drawn by default: each base kind with a stop event (highway_stops).
EXTRA_KINDS: tuple[str, ...] = tuple(kind + STOP_SUFFIX for kind in KINDS)


class SceneCrashError(RuntimeError):
    """Every attempt at a scene ended in a crash involving the ego (or another recorded vehicle)."""


@dataclass(frozen=True)
class HighwaySceneConfig:
    """Settings of one generated scene.

    ``density`` scales each kind's traffic (vehicle counts / spacing; two-way and u-turn keep
    highway-env's fixed traffic); ``warmup_seconds`` are simulated before the first recorded step;
    ``map_spacing`` (m) is the largest gap between map points; ``agent_radius`` drops vehicles
    that never come within that many metres of the sdc (None keeps all); ``map_margin`` is how far
    (m) the map extends beyond the recorded vehicles; ``reject_any_crash`` retries scenes in which any
    recorded vehicle crashes (the ego's crashes are always retried), up to ``max_attempts``;
    ``kerb_radius`` (m) rounds the kerb corners where one road edge hands over to the next (highway-env's
    vehicles cut those corners: with sharp corners 53-62 % of the logged roundabout vehicles crossed an
    edge, with 8 m none did; 0 keeps them sharp).
    """

    steps: int = 91
    current_index: int = 10
    dt: float = 0.1
    substeps: int = 1
    warmup_seconds: float = 2.0
    map_spacing: float = 0.5
    map_margin: float = 50.0
    density: float = 1.0
    agent_radius: float | None = 150.0
    reject_any_crash: bool = True
    max_attempts: int = 8
    kerb_radius: float = 8.0

    def __post_init__(self) -> None:
        checks = {
            "steps": self.steps >= 2,
            "current_index": 0 <= self.current_index < self.steps,
            "dt": self.dt > 0,
            "substeps": self.substeps >= 1,
            "warmup_seconds": self.warmup_seconds >= 0,
            "map_spacing": 0 < self.map_spacing <= 5,
            "map_margin": self.map_margin >= 0,
            "density": self.density > 0,
            "agent_radius": self.agent_radius is None or self.agent_radius > 0,
            "max_attempts": self.max_attempts >= 1,
            "kerb_radius": self.kerb_radius >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"HighwaySceneConfig.{name}: invalid value {getattr(self, name)!r}")


@functools.cache
def _env(kind: str, sim_frequency: int) -> AbstractEnv:
    """One env object per kind and process: ``reset(seed=..., options=config)`` rebuilds its whole scene."""
    spec = KIND_SPECS[kind]
    return spec.env_class(config=base_env_config(spec, sim_frequency))


def _remove_departed(road: Road, keep: Vehicle) -> None:
    """Drop vehicles (other than ``keep``) that drove past the end of a lane with no successor."""
    graph = road.network.graph
    departed = [
        v
        for v in road.vehicles
        if v is not keep
        and not graph.get(v.lane_index[1])
        and v.lane.local_coordinates(v.position)[0] > v.lane.length
    ]
    for v in departed:
        road.vehicles.remove(v)


@dataclass(frozen=True)
class _Recording:
    """Raw tracks in highway-env's frame: states ``[N, T, 3]``, validity, crash flags, sdc row."""

    xyh: np.ndarray
    valid: np.ndarray
    size: np.ndarray
    crashed: np.ndarray
    sdc: int
    stopper: int | None = None  # row of a stop event's vehicle


def _simulate(
    env: AbstractEnv, spec: KindSpec, sdc: Vehicle, config: HighwaySceneConfig, stop: StopEvent | None = None
) -> _Recording | None:
    """Warm up, then record ``config.steps`` states of every vehicle; None if the sdc crashes. With a
    ``stop`` event, its vehicle starts braking to a stop at the event's recorded step."""
    road = env.road
    sim_dt = config.dt / config.substeps
    warmup = int(round(config.warmup_seconds / sim_dt))
    last = warmup + (config.steps - 1) * config.substeps
    policy_period = int(round(1.0 / sim_dt))
    rows: dict[int, int] = {}
    tracked: list[Vehicle] = []  # keeps every recorded vehicle alive, so id() values stay unique
    records: list[tuple[int, int, float, float, float]] = []
    crashed: set[int] = set()
    stopper = None
    for k in range(last + 1):
        if k > 0:
            if spec.spawns_traffic and k % policy_period == 0:
                env._clear_vehicles()
                env._spawn_vehicle(spawn_probability=env.config["spawn_probability"])
            _remove_departed(road, sdc)
            road.act()
            road.step(sim_dt)
            if sdc.crashed:
                return None
        if k < warmup or (k - warmup) % config.substeps:
            continue
        t = (k - warmup) // config.substeps
        if stop is not None and t == stop.step:
            stopper = choose_stopper(road, sdc, stop)
            if stopper is not None:
                start_stop(stopper, stop)
        for v in road.vehicles:
            row = rows.get(id(v))
            if row is None:
                row = rows[id(v)] = len(tracked)
                tracked.append(v)
            records.append((row, t, v.position[0], v.position[1], v.heading))
            if v.crashed:
                crashed.add(row)
    data = np.array(records, dtype=np.float64)
    row, step = data[:, 0].astype(np.int64), data[:, 1].astype(np.int64)
    xyh = np.zeros((len(tracked), config.steps, 3))
    valid = np.zeros((len(tracked), config.steps), dtype=bool)
    xyh[row, step] = data[:, 2:]
    valid[row, step] = True
    size = np.array([[v.LENGTH, v.WIDTH] for v in tracked], dtype=np.float64)
    crashed_mask = np.isin(np.arange(len(tracked)), sorted(crashed))
    stop_row = None if stopper is None else rows[id(stopper)]
    return _Recording(xyh, valid, size, crashed_mask, rows[id(sdc)], stop_row)


def _to_scenario_frame(xyh: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Mirror y (highway-env screen frame -> right-handed): ``(x, -y, -heading)``, zeros where invalid."""
    out = np.stack([xyh[..., 0], -xyh[..., 1] + 0.0, wrap_angle(-xyh[..., 2])], -1)  # + 0.0: no -0.0
    return np.where(valid[..., None], out, 0.0)


def _near_sdc(xyh: np.ndarray, valid: np.ndarray, sdc: int, radius: float | None) -> np.ndarray:
    """Mask of agents that come within ``radius`` metres of the sdc at some step where both exist."""
    if radius is None:
        return valid.any(axis=1)
    dist = np.linalg.norm(xyh[:, :, :2] - xyh[sdc, None, :, :2], axis=-1)
    dist = np.where(valid & valid[sdc], dist, np.inf)
    return dist.min(axis=1) <= radius


def _tracks_to_predict(
    xyh: np.ndarray, valid: np.ndarray, sdc: int, current: int, limit: int = 8
) -> np.ndarray:
    """Up to ``limit`` agents (not the sdc) valid at every step, nearest to the sdc at ``current`` first."""
    candidates = np.flatnonzero(valid.all(axis=1) & (np.arange(len(valid)) != sdc))
    dist = np.linalg.norm(xyh[candidates, current, :2] - xyh[sdc, current, :2], axis=-1)
    return np.sort(candidates[np.argsort(dist, kind="stable")[:limit]]).astype(np.int64)


def _attempt(kind: str, seed: int, attempt: int, config: HighwaySceneConfig) -> Scenario | None:
    """Build and record one try of a scene; None when it has to be retried (a crash)."""
    kind, stops = split_kind(kind)
    spec = KIND_SPECS[kind]
    env_seed, config_seed = np.random.SeedSequence([seed, attempt]).generate_state(2)
    rng = np.random.default_rng(int(config_seed))
    sim_frequency = int(round(config.substeps / config.dt))
    env = _env(kind, sim_frequency)
    options = {**base_env_config(spec, sim_frequency), **spec.env_config(rng, config.density)}
    env.reset(seed=int(env_seed), options={"config": options})
    if spec.prepare is not None:
        spec.prepare(env, rng, config.density)
    road = env.road
    ego_index = next(i for i, v in enumerate(road.vehicles) if v is env.vehicle)
    road.vehicles[:] = [as_scene_vehicle(v, spec.idm_class) for v in road.vehicles]
    if not spec.lane_changes:
        for vehicle in road.vehicles:
            vehicle.enable_lane_change = False
    if spec.sdc_in_platoon:
        n = len(road.vehicles)
        ego_index = int(rng.integers(n // 4, max(n // 2, n // 4 + 1)))
    sdc = road.vehicles[ego_index]
    env.controlled_vehicles = [sdc]
    stop = draw_stop_event(seed, attempt, config.current_index, config.steps) if stops else None
    recording = _simulate(env, spec, sdc, config, stop)
    if recording is None:
        return None
    xyh = _to_scenario_frame(recording.xyh, recording.valid)
    keep = _near_sdc(xyh, recording.valid, recording.sdc, config.agent_radius)
    if config.reject_any_crash and (recording.crashed & keep).any():
        return None
    index = np.flatnonzero(keep)
    xyh, valid = xyh[index], recording.valid[index]
    sdc_index = int(np.flatnonzero(index == recording.sdc)[0])
    points = xyh[valid][:, :2]
    region = (points.min(axis=0) - config.map_margin, points.max(axis=0) + config.map_margin)
    map_lines = network_polylines(
        road.network, spec.lane_kind, region, spacing=config.map_spacing, kerb_radius=config.kerb_radius
    )
    return Scenario.from_arrays(
        xyh,
        valid,
        recording.size[index],
        np.full(len(index), AgentKind.VEHICLE, dtype=np.int8),
        track_id=index.astype(np.int64),
        sdc=sdc_index,
        polylines=map_lines.polylines,
        polyline_kinds=map_lines.kinds,
        scenario_id=f"{SOURCE}-{kind}{STOP_SUFFIX if stops else ''}-{seed}"
        + stop_id_suffix(stop, recording.stopper if recording.stopper in index else None),
        source=SOURCE,
        dt=float(config.dt),
        current_index=int(config.current_index),
        tracks_to_predict=_tracks_to_predict(xyh, valid, sdc_index, config.current_index),
    )


def check_kind(kind: str) -> None:
    """A ValueError naming the known kinds unless ``kind`` is one of KINDS or EXTRA_KINDS."""
    if kind not in KINDS and kind not in EXTRA_KINDS:
        raise ValueError(f"unknown highway scene kind {kind!r}; expected one of {KINDS + EXTRA_KINDS}")


def generate_scene(kind: str, seed: int, config: HighwaySceneConfig = HighwaySceneConfig()) -> Scenario:
    """Simulate one scene of ``kind`` (one of :data:`KINDS` or :data:`EXTRA_KINDS`); a pure function of its
    arguments.

    A crash involving the ego (or, with ``config.reject_any_crash``, any kept vehicle) retries with a
    seed derived from (seed, attempt); after ``config.max_attempts`` tries a SceneCrashError is raised.
    """
    check_kind(kind)
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    for attempt in range(config.max_attempts):
        scene = _attempt(kind, int(seed), attempt, config)
        if scene is not None:
            return scene
    raise SceneCrashError(
        f"highway scene kind {kind!r} seed {seed}: a vehicle crashed in all {config.max_attempts} attempts; "
        "raise HighwaySceneConfig.max_attempts or lower its density"
    )


def generate_shard(
    kinds: tuple[str, ...], seed: int, shard_index: int, count: int, capacity: int | None = None
) -> list[Scenario]:
    """``count`` scenes of shard ``shard_index``; slot ``i`` uses ``scene_seed(seed, shard_index, i)`` (so a
    partial shard holds the first scenes of a full one whatever ``capacity``).

    The kind of each scene is drawn from ``kinds`` (all :data:`KINDS` when empty) by its own seed.
    """
    kinds = tuple(kinds) or KINDS
    for kind in kinds:
        check_kind(kind)
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    scenes = []
    for slot in range(count):
        s = scene_seed(seed, shard_index, slot)
        scenes.append(generate_scene(kinds[s % len(kinds)], s))
    return scenes
