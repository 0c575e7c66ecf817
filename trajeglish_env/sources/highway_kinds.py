"""The scene kinds of the highway-env source: which env builds each, how its traffic is randomized,
and the IDM/MOBIL vehicle class that drives every car (ego included).

Each kind's env config is drawn from the scene's own RNG (``density`` scales the traffic), so one
seed gives one scene. The IDM parameters are pinned on :class:`SceneIDMVehicle` (highway-env's
``IntersectionEnv`` writes gap/comfort parameters onto the class it is given; pinning keeps such
writes, by it or by anyone else in the process, away from the other kinds).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.exit_env import ExitEnv
from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeGenericEnv
from highway_env.envs.racetrack_env import RacetrackEnv
from highway_env.envs.roundabout_env import RoundaboutGenericEnv
from highway_env.envs.two_way_env import TwoWayEnv
from highway_env.envs.u_turn_env import UTurnEnv
from highway_env.road.regulation import RegulatedRoad
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from trajeglish_env.scenario import MapKind

KINDS: tuple[str, ...] = (
    "highway",
    "merge",
    "roundabout",
    "intersection",
    "exit",
    "two-way",
    "u-turn",
    "racetrack",
)


class SceneIDMVehicle(IDMVehicle):
    """highway-env's IDM/MOBIL vehicle with its parameters pinned here, and no reversing.

    IDM can ask for more braking than the remaining speed (e.g. while yielding); highway-env would
    then roll the car backwards. We clip the deceleration so a stopping car stops at zero speed.
    """

    ACC_MAX = 6.0
    COMFORT_ACC_MAX = 3.0
    COMFORT_ACC_MIN = -5.0
    DISTANCE_WANTED = 5.0 + Vehicle.LENGTH
    TIME_WANTED = 1.5
    DELTA = 4.0
    DELTA_RANGE = (3.5, 4.5)
    POLITENESS = 0.0
    LANE_CHANGE_MIN_ACC_GAIN = 0.2
    LANE_CHANGE_MAX_BRAKING_IMPOSED = 2.0
    LANE_CHANGE_DELAY = 1.0
    stop_decel = 0.0  # > 0: brake at this rate (m/s^2) to a stop and hold (highway_stops.start_stop)

    def act(self, action: dict | str | None = None) -> None:
        """IDM/MOBIL, or a constant braking rate once a stop event has started (steering still follows
        the lane)."""
        super().act(action)
        if self.stop_decel > 0 and not self.crashed:
            self.action["acceleration"] = -self.stop_decel

    def step(self, dt: float) -> None:
        """Advance the bicycle model by ``dt`` seconds, never below zero speed."""
        if not self.crashed and self.speed >= 0:
            self.action["acceleration"] = max(float(self.action["acceleration"]), -self.speed / dt)
        super().step(dt)

    def predict_trajectory_constant_speed(self, times: np.ndarray) -> tuple[list[np.ndarray], list[float]]:
        """highway-env's constant-speed route prediction (used by RegulatedRoad), with each route step's
        lane id bounded by that road's lane count (highway-env reuses the current id, which need not exist
        on a narrower next road)."""
        route = self.route
        if route:
            graph, current = self.road.network.graph, self.lane_index[2]
            self.route = [(a, b, min(current, len(graph[a][b]) - 1) if i is None else i) for a, b, i in route]
        try:
            return super().predict_trajectory_constant_speed(times)
        finally:
            self.route = route


class IntersectionIDMVehicle(SceneIDMVehicle):
    """The IDM class handed to ``IntersectionEnv``, which sets its gap/comfort parameters on it."""


def _class_path(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


# ----------------------------------------------------------------------------------- scene kinds
def _uniform_int(rng: np.random.Generator, low: float, high: float) -> int:
    return max(int(round(rng.uniform(low, high))), 1)


@dataclass(frozen=True)
class KindSpec:
    """How one scene kind is built: env class, its randomized config, map lane kind, sdc choice."""

    env_class: type[AbstractEnv]
    lane_kind: MapKind
    env_config: Callable[[np.random.Generator, float], dict]
    idm_class: type[SceneIDMVehicle] = SceneIDMVehicle
    # The env puts its ego behind all other traffic; pick the sdc inside the platoon instead.
    sdc_in_platoon: bool = False
    # Scene kinds whose env spawns/clears vehicles once per policy step (1 s).
    spawns_traffic: bool = False
    # Adjusts the freshly reset env (rng, density) before its vehicles become SceneIDMVehicles.
    prepare: Callable[[AbstractEnv, np.random.Generator, float], None] | None = None
    # False: no vehicle changes lanes (two-way: the left lane is the oncoming traffic's, which MOBIL does
    # not see: the sdc overtook into it and drove the whole log head-on at oncoming cars)
    lane_changes: bool = True


_ROUNDABOUT_RING = frozenset({"se", "ex", "ee", "nx", "ne", "wx", "we", "sx"})


def _regulate_roundabout(env: AbstractEnv, rng: np.random.Generator, density: float) -> None:
    """Give the ring right of way, as highway-env's intersection does: a RegulatedRoad makes entering
    vehicles yield to ring traffic (without it IDM cars merge blindly and crash in most scenes).
    Speed limits become 10 m/s on the ring and 14 m/s elsewhere (highway-env's 20 m/s default gives
    over 1 g of lateral acceleration on a 20 m ring)."""
    road = env.road
    for (start, end, _), lane in road.network.lanes_dict().items():
        on_ring = start in _ROUNDABOUT_RING and end in _ROUNDABOUT_RING
        lane.priority = 1 if on_ring else 0
        lane.speed_limit = 10.0 if on_ring else 14.0
    regulated = RegulatedRoad(
        network=road.network,
        vehicles=road.vehicles,
        obstacles=road.objects,
        np_random=road.np_random,
        neighbour_vehicles_connected_lanes=road.neighbour_vehicles_connected_lanes,
    )
    for vehicle in regulated.vehicles:
        vehicle.road = regulated
    env.road = regulated


def _populate_racetrack(env: AbstractEnv, rng: np.random.Generator, density: float) -> None:
    """The racetrack env places at most a few cars; add more on random lanes, 15 m apart at least."""
    road = env.road
    lanes = list(road.network.lanes_dict().items())
    for _ in range(_uniform_int(rng, 6 * density, 12 * density)):
        for _ in range(10):
            index, lane = lanes[int(rng.integers(len(lanes)))]
            longitudinal = float(rng.uniform(0.0, lane.length))
            position = lane.position(longitudinal, 0.0)
            if all(np.linalg.norm(position - v.position) > 15.0 for v in road.vehicles):
                speed = float(rng.uniform(6.0, 9.0))
                road.vehicles.append(SceneIDMVehicle.make_on_lane(road, index, longitudinal, speed))
                break


KIND_SPECS: dict[str, KindSpec] = {
    "highway": KindSpec(
        HighwayEnv,
        MapKind.LANE_FREEWAY,
        lambda rng, d: {
            "lanes_count": int(rng.integers(2, 5)),
            "vehicles_count": 20,
            "vehicles_density": d * rng.uniform(0.5, 1.3),
            "ego_spacing": 1.0,
        },
        sdc_in_platoon=True,
    ),
    "merge": KindSpec(
        MergeGenericEnv,
        MapKind.LANE_FREEWAY,
        lambda rng, d: {
            "lanes_count": int(rng.integers(2, 4)),
            "vehicles_count": _uniform_int(rng, 5 * d, 10 * d),
            "after_merge_length": 450,
        },
    ),
    "roundabout": KindSpec(
        RoundaboutGenericEnv,
        MapKind.LANE_SURFACE_STREET,
        lambda rng, d: {
            "vehicles_count": _uniform_int(rng, 6 * d, 12 * d),
            "roundabout_lanes": int(rng.integers(1, 3)),
            "roundabout_radius": float(rng.uniform(18.0, 28.0)),
        },
        prepare=_regulate_roundabout,
    ),
    "intersection": KindSpec(
        IntersectionEnv,
        MapKind.LANE_SURFACE_STREET,
        lambda rng, d: {
            "initial_vehicle_count": _uniform_int(rng, 8 * d, 14 * d),
            "spawn_probability": float(min(rng.uniform(0.5, 0.8) * d, 1.0)),
            "destination": None,
        },
        idm_class=IntersectionIDMVehicle,
        spawns_traffic=True,
    ),
    "exit": KindSpec(
        ExitEnv,
        MapKind.LANE_FREEWAY,
        lambda rng, d: {
            "lanes_count": int(rng.integers(3, 6)),
            "vehicles_count": 16,
            "vehicles_density": d * rng.uniform(0.8, 1.6),
            "ego_spacing": 1.0,
        },
        sdc_in_platoon=True,
    ),
    "two-way": KindSpec(TwoWayEnv, MapKind.LANE_SURFACE_STREET, lambda rng, d: {}, lane_changes=False),
    "u-turn": KindSpec(UTurnEnv, MapKind.LANE_SURFACE_STREET, lambda rng, d: {}),
    "racetrack": KindSpec(
        RacetrackEnv,
        MapKind.LANE_SURFACE_STREET,
        lambda rng, d: {"other_vehicles": 1},
        prepare=_populate_racetrack,
    ),
}
assert set(KIND_SPECS) == set(KINDS)


def base_env_config(spec: KindSpec, sim_frequency: int) -> dict:
    """Env settings shared by all kinds: our IDM class, our rate, the cheapest observation."""
    return {
        "simulation_frequency": sim_frequency,
        "policy_frequency": 1,
        "other_vehicles_type": _class_path(spec.idm_class),
        "observation": {"type": "Kinematics", "vehicles_count": 1},
        "show_trajectories": False,
    }


def check_kind(kind: str) -> KindSpec:
    """The spec of scene ``kind``; a ValueError naming the known kinds otherwise."""
    if kind not in KIND_SPECS:
        raise ValueError(f"unknown highway scene kind {kind!r}; expected one of {KINDS}")
    return KIND_SPECS[kind]


def as_scene_vehicle(vehicle: Vehicle, cls: type[SceneIDMVehicle]) -> SceneIDMVehicle:
    """The same car (state, route, target lane and speed) as an IDM/MOBIL vehicle of class ``cls``."""
    if type(vehicle) is cls:
        return vehicle
    if isinstance(vehicle, ControlledVehicle):
        new = cls.create_from(vehicle)
    else:
        speed = vehicle.speed if vehicle.speed is not None else (vehicle.lane.speed_limit or 10.0)
        new = cls(vehicle.road, vehicle.position, vehicle.heading, speed)
    new.randomize_behavior()
    return new
