"""All per-step realism features of a batch of trajectories of one scene (WOSAC §2).

:func:`prepare_scene` turns a Scenario (plus optional raw :class:`LogDetails`) into the float32 inputs
of the metrics: which agents are simulated and evaluated, the logged tracks, the current boxes, road
edges and traffic signals. :func:`compute_features` then evaluates every feature over the future steps
of ``B`` full-length trajectories (the log, rollouts, or both stacked).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.metrics.interaction import interaction_features
from trajeglish_env.metrics.kinematics import kinematic_features, linear_speed
from trajeglish_env.metrics.log_details import TYPE_VEHICLE, LogDetails
from trajeglish_env.metrics.road_edges import OFFROAD_THRESHOLD, RoadEdges, distance_to_road_edge
from trajeglish_env.metrics.traffic_lights import TrafficSignals, red_light_violations
from trajeglish_env.scenario import ROAD_EDGE_KINDS, MapKind, Scenario

__all__ = ["MetricScene", "RealismFeatures", "compute_features", "prepare_scene"]


@dataclass(frozen=True, eq=False)
class MetricScene:
    """One scene ready for scoring (float32 arrays over the N simulated agents and all T steps).

    Simulated agents are those valid at the current step, ordered evaluated first (by track id), then the
    others (by track id); ``num_evaluated`` leading agents are scored. ``agent_index [N]`` points back
    into the Scenario.
    """

    scenario_id: str
    dt: float
    current: int
    track_id: np.ndarray
    agent_index: np.ndarray
    num_evaluated: int
    log_xyz: np.ndarray
    log_heading: np.ndarray
    log_valid: np.ndarray
    box: np.ndarray
    is_vehicle: np.ndarray
    road_edges: RoadEdges
    signals: TrafficSignals

    @property
    def num_simulated(self) -> int:
        return int(self.track_id.shape[0])

    @property
    def num_future(self) -> int:
        return int(self.log_valid.shape[1]) - self.current - 1

    @property
    def evaluated(self) -> np.ndarray:
        """Indices (into the simulated agents) of the evaluated ones."""
        return np.arange(self.num_evaluated)


def evaluated_agents(scenario: Scenario, simulated: np.ndarray) -> np.ndarray:
    """Agent indices scored: the sdc and the agents to predict (all simulated agents if none is named)."""
    if len(scenario.tracks_to_predict) == 0:
        return simulated
    chosen = np.union1d([scenario.sdc], scenario.tracks_to_predict).astype(np.int64)
    late = chosen[~scenario.valid[chosen, scenario.current_index]]
    if len(late):
        raise ValueError(
            f"scenario {scenario.scenario_id!r}: evaluated agent(s) with track id "
            f"{scenario.track_id[late].tolist()} are not valid at the current step {scenario.current_index}"
        )
    return chosen


def prepare_scene(scenario: Scenario, details: LogDetails | None = None) -> MetricScene:
    """The metrics' view of ``scenario``; ``details`` default to :meth:`LogDetails.planar` (z = 0)."""
    details = LogDetails.planar(scenario) if details is None else details
    details.check_matches(scenario)
    if scenario.current_index + 1 >= scenario.num_steps:
        raise ValueError(f"scenario {scenario.scenario_id!r}: no future step after current_index")
    simulated = np.flatnonzero(scenario.valid[:, scenario.current_index])
    evaluated = evaluated_agents(scenario, simulated)
    ev_sorted = evaluated[np.argsort(scenario.track_id[evaluated], kind="stable")]
    others = np.setdiff1d(simulated, evaluated)
    order = np.concatenate([ev_sorted, others[np.argsort(scenario.track_id[others], kind="stable")]])

    edge_lines, lanes, lane_ids = [], [], []
    for k in range(scenario.num_polylines):
        lo, hi = scenario.map_offsets[k], scenario.map_offsets[k + 1]
        if scenario.map_kind[k] in ROAD_EDGE_KINDS:
            edge_lines.append(np.column_stack([scenario.map_points[lo:hi], details.map_z[lo:hi]]))
        elif scenario.map_kind[k] == MapKind.LANE_SURFACE_STREET:
            lanes.append(scenario.map_points[lo:hi])
            lane_ids.append(int(scenario.map_id[k]))
    try:
        road_edges = RoadEdges.from_polylines(edge_lines)
    except ValueError as exc:
        raise ValueError(f"scenario {scenario.scenario_id!r}: {exc}") from exc
    states = scenario.signal_state
    signals = TrafficSignals.build(
        lanes,
        lane_ids,
        scenario.signal_lane_id,
        np.zeros((scenario.num_steps, 0), np.int64) if states is None else states,
        details.signal_stop,
    )
    f32 = np.float32
    return MetricScene(
        scenario_id=scenario.scenario_id,
        dt=float(scenario.dt),
        current=int(scenario.current_index),
        track_id=scenario.track_id[order],
        agent_index=order,
        num_evaluated=len(evaluated),
        log_xyz=details.xyz[order].astype(f32),
        log_heading=details.heading[order].astype(f32),
        log_valid=scenario.valid[order],
        box=details.box[order].astype(f32),
        is_vehicle=details.object_type[order] == TYPE_VEHICLE,
        road_edges=road_edges,
        signals=signals,
    )


@dataclass(frozen=True, eq=False)
class RealismFeatures:
    """Per-step features ``[B, E, T_future]`` of the evaluated agents (float32, or bool for indicators)."""

    linear_speed: np.ndarray
    linear_acceleration: np.ndarray
    angular_speed: np.ndarray
    angular_acceleration: np.ndarray
    distance_to_nearest_object: np.ndarray
    collision: np.ndarray
    time_to_collision: np.ndarray
    distance_to_road_edge: np.ndarray
    offroad: np.ndarray
    traffic_light_violation: np.ndarray


def compute_features(
    scene: MetricScene, xyz: np.ndarray, heading: np.ndarray, valid: np.ndarray
) -> RealismFeatures:
    """Features of ``B`` full trajectories ``xyz [B, N, T, 3]``, ``heading [B, N, T]``, ``valid [B, N, T]``
    of the scene's simulated agents (history included: kinematics at the first future steps use it)."""
    n, t = scene.log_valid.shape
    b = xyz.shape[0]
    if xyz.shape != (b, n, t, 3) or heading.shape != (b, n, t) or valid.shape != (b, n, t):
        raise ValueError(
            f"compute_features: expected xyz [B, {n}, {t}, 3], heading and valid [B, {n}, {t}]; got "
            f"{xyz.shape}, {heading.shape}, {valid.shape}"
        )
    xyz, heading = xyz.astype(np.float32, copy=False), heading.astype(np.float32, copy=False)
    ev, future = scene.evaluated, slice(scene.current + 1, t)
    kinematic = kinematic_features(xyz[:, ev], heading[:, ev], scene.dt)
    # 2-D speed over the future (central differences need step g - 1; NaN at the last step).
    speed_2d = linear_speed(xyz[:, :, future.start - 1 : t, :2], scene.dt)[..., 1:]
    interactions = interaction_features(
        xyz[:, :, future, :2], heading[:, :, future], valid[:, :, future], scene.box[:, :2], speed_2d, ev
    )
    road = distance_to_road_edge(
        xyz[:, ev, future],
        heading[:, ev, future],
        scene.box[ev][None, :, None, :],
        valid[:, ev, future],
        scene.road_edges,
    )
    current = scene.current
    lights = red_light_violations(scene.signals, xyz[:, ev, current:, :2], valid[:, ev, current:], current)
    return RealismFeatures(
        **{name: kinematic[name][..., future] for name in kinematic},
        distance_to_nearest_object=interactions.distance_to_nearest_object,
        collision=interactions.collision,
        time_to_collision=interactions.time_to_collision,
        distance_to_road_edge=road,
        offroad=road > OFFROAD_THRESHOLD,
        traffic_light_violation=lights,
    )
