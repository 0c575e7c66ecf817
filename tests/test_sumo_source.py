"""The SUMO urban scene source: classes, kinematics, geometry, map, signals, determinism, errors.

One small shard (one SUMO simulation of a signalized grid) is generated once per module; the checks
run on its scenes and on the raw simulation they were cut from.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from trajeglish_env.geometry import box_corners, wrap_angle
from trajeglish_env.scenario import (
    LANE_KINDS,
    ROAD_EDGE_KINDS,
    ROAD_LINE_KINDS,
    AgentKind,
    MapKind,
    Scenario,
    SignalState,
)
from trajeglish_env.scenario_io import load_scenarios, save_scenarios

sumo = pytest.importorskip("trajeglish_env.sources.sumo")
from trajeglish_env.sources import sumo_map, sumo_sim, sumo_tools  # noqa: E402
from trajeglish_env.sources.sumo_demand import AgentType  # noqa: E402
from trajeglish_env.sources.sumo_net import Lane, SumoNet  # noqa: E402
from trajeglish_env.sources.sumo_sim import DT  # noqa: E402

SEED, SHARD, COUNT, KINDS = 3, 0, 4, ("grid",)


@pytest.fixture(scope="module")
def run() -> sumo_sim.SumoRun:
    try:
        return sumo.simulate_shard(KINDS, SEED, SHARD, COUNT)
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))


@pytest.fixture(scope="module")
def scenes(run: sumo_sim.SumoRun) -> list[Scenario]:
    return sumo.cut_scenes(run, SEED, SHARD, COUNT)


def _motion(scene: Scenario, kinds: tuple[AgentKind, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Speed, heading-vs-motion error and heading change [N,T-1] of agents of ``kinds`` (NaN: invalid)."""
    rows = np.isin(scene.kind, kinds)
    xyh, valid = scene.xyh[rows], scene.valid[rows]
    step = np.diff(xyh[..., :2], axis=1)
    both = valid[:, 1:] & valid[:, :-1]
    speed = np.linalg.norm(step, axis=-1) / scene.dt
    direction_error = np.abs(wrap_angle(np.arctan2(step[..., 1], step[..., 0]) - xyh[:, 1:, 2]))
    turn = np.abs(wrap_angle(np.diff(xyh[..., 2], axis=1)))
    return (
        np.where(both, speed, np.nan),
        np.where(both, direction_error, np.nan),
        np.where(both, turn, np.nan),
    )


def _overlaps(
    xyh: np.ndarray, size: np.ndarray, valid: np.ndarray, shrink: float
) -> list[tuple[int, int, int]]:
    """(step, i, j) of every pair of boxes that overlap (separating axes; boxes shrunk by ``shrink`` m)."""
    corners = box_corners(xyh, np.maximum(size[:, None, :] - shrink, 0.05))  # [N,T,4,2]
    reach = 0.5 * np.linalg.norm(size, axis=1)  # half diagonal: boxes farther apart cannot touch
    found = []
    for t in range(xyh.shape[1]):
        idx = np.flatnonzero(valid[:, t])
        i, j = np.triu_indices(len(idx), k=1)
        close = (
            np.linalg.norm(xyh[idx[i], t, :2] - xyh[idx[j], t, :2], axis=-1) < reach[idx[i]] + reach[idx[j]]
        )
        i, j = i[close], j[close]
        a, b = corners[idx[i], t], corners[idx[j], t]
        edges = np.concatenate([a[:, 1:] - a[:, :1], b[:, 1:] - b[:, :1]], axis=1)[:, [0, 2, 3, 5]]
        axes = np.stack([-edges[..., 1], edges[..., 0]], axis=-1)  # [P,4,2]
        pa, pb = np.einsum("pkd,pcd->pkc", axes, a), np.einsum("pkd,pcd->pkc", axes, b)
        separated = (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
        hit = ~separated.any(axis=1)
        found += [(t, int(idx[p]), int(idx[q])) for p, q in zip(i[hit], j[hit], strict=True)]
    return found


def _distance_to_polylines(points: np.ndarray, lines: list[np.ndarray]) -> np.ndarray:
    """Distance of each point [M,2] to the nearest segment of any polyline (segments within 10 m only)."""
    starts = np.concatenate([p[:-1] for p in lines])
    seg = np.concatenate([p[1:] for p in lines]) - starts
    out = np.full(len(points), np.inf)
    for m, point in enumerate(points):
        near = np.abs(starts - point).max(axis=1) < 10.0
        rel, s = point - starts[near], seg[near]
        t = np.clip(np.sum(rel * s, -1) / np.maximum(np.sum(s * s, -1), 1e-9), 0.0, 1.0)
        out[m] = np.linalg.norm(rel - t[:, None] * s, axis=-1).min(initial=np.inf)
    return out


# ---------------------------------------------------------------------------------------------- scenes
def test_scenes_are_womd_like(scenes: list[Scenario]) -> None:
    assert len(scenes) == COUNT
    assert len({s.scenario_id for s in scenes}) == COUNT
    for scene in scenes:
        scene.validate()
        assert scene.source == "sumo" and scene.dt == pytest.approx(0.1) and scene.current_index == 10
        assert scene.num_steps == 91 and 10 <= scene.num_agents <= 128
        assert scene.kind[scene.sdc] == AgentKind.VEHICLE and scene.valid[scene.sdc].all()
        assert scene.valid.any(axis=1).all(), "agents that are never valid must be dropped"
        gap = np.linalg.norm(scene.xyh[..., :2] - scene.xyh[scene.sdc, None, :, :2], axis=-1)
        assert gap[scene.valid].max() <= 80.0, "agents are valid only within perception range of the sdc"
        assert (scene.xyh[~scene.valid] == 0.0).all()
        assert scene.valid[scene.tracks_to_predict].all()


def test_agents_enter_and_leave_through_valid(scenes: list[Scenario]) -> None:
    assert sum(int((~s.valid[:, 0]).sum()) for s in scenes) >= 1
    assert sum(int((~s.valid[:, -1]).sum()) for s in scenes) >= 1


def test_every_class_is_present_with_sumo_sizes(scenes: list[Scenario]) -> None:
    for scene in scenes:
        counts = np.bincount(scene.kind, minlength=3)
        assert counts[AgentKind.VEHICLE] >= 5 and counts[AgentKind.PEDESTRIAN] >= 1, counts
    assert sum(np.bincount(s.kind, minlength=3)[AgentKind.CYCLIST] for s in scenes) >= 1
    scene = scenes[0]
    size = {k: scene.size[scene.kind == k] for k in AgentKind}
    assert ((size[AgentKind.VEHICLE][:, 0] >= 3.8) & (size[AgentKind.VEHICLE][:, 0] <= 13.0)).all()
    assert ((size[AgentKind.PEDESTRIAN] >= 0.45) & (size[AgentKind.PEDESTRIAN] <= 0.7)).all()
    assert ((size[AgentKind.CYCLIST][:, 0] >= 1.6) & (size[AgentKind.CYCLIST][:, 0] <= 1.9)).all()


def test_speeds_are_plausible_per_class(scenes: list[Scenario]) -> None:
    speed = {k: np.concatenate([_motion(s, (k,))[0].ravel() for s in scenes]) for k in AgentKind}
    walking = speed[AgentKind.PEDESTRIAN][speed[AgentKind.PEDESTRIAN] > 0.2]
    assert 0.5 <= np.median(walking) <= 2.0 and np.nanmax(speed[AgentKind.PEDESTRIAN]) < 3.5
    driving = speed[AgentKind.VEHICLE][speed[AgentKind.VEHICLE] > 0.5]
    assert 3.0 <= np.median(driving) <= 15.0 and np.nanmax(speed[AgentKind.VEHICLE]) < 25.0
    riding = speed[AgentKind.CYCLIST][speed[AgentKind.CYCLIST] > 0.5]
    assert 1.0 <= np.median(riding) <= 8.0 and np.nanpercentile(speed[AgentKind.CYCLIST], 99.9) < 8.0
    assert np.nanmax(speed[AgentKind.CYCLIST]) < 15.0


def test_headings_follow_motion_and_are_continuous(scenes: list[Scenario]) -> None:
    speed, direction_error, turn = (
        np.concatenate([m.ravel() for m in parts])
        for parts in zip(*[_motion(s, (AgentKind.VEHICLE, AgentKind.CYCLIST)) for s in scenes], strict=True)
    )
    # SUMO's clockwise-from-north degrees became radians counter-clockwise from +x. (A box centre's
    # motion legitimately deviates from the heading in tight turns, and where SUMO slides a slow
    # vehicle sideways into another lane.)
    errors = direction_error[speed > 2.0]
    assert np.median(errors) < 0.03 and np.percentile(errors, 95) < 0.2 and np.mean(errors > 1.0) < 0.005
    assert np.nanmax(turn) < 0.5, "no 2*pi (or lane-change) jumps in vehicle or cyclist headings"
    assert all((np.abs(s.xyh[..., 2]) <= np.pi).all() for s in scenes)
    # Pedestrians turn sharply only when they set off after waiting (e.g. at a crossing).
    walker_turn = np.concatenate([_motion(s, (AgentKind.PEDESTRIAN,))[2].ravel() for s in scenes])
    walker_turn = walker_turn[np.isfinite(walker_turn)]
    assert np.percentile(walker_turn, 99) < 0.5 and np.mean(walker_turn > 1.0) < 0.01


def test_vehicle_boxes_are_centred_on_lanes(run: sumo_sim.SumoRun) -> None:
    net_map = run.net_map
    lanes = [
        net_map.points[a:b]
        for a, b, k in zip(net_map.offsets[:-1], net_map.offsets[1:], net_map.kind, strict=True)
        if k in LANE_KINDS
    ]
    speed = np.linalg.norm(np.gradient(run.xyh[..., :2], DT, axis=1), axis=-1)
    moving = (run.kind == AgentKind.VEHICLE)[:, None] & run.valid & ~run.on_junction & (speed > 2.0)
    points = run.xyh[moving][:, :2]
    distance = _distance_to_polylines(points[:: max(1, len(points) // 400)], lanes)  # 400 samples are plenty
    # Away from junctions: mostly on a lane centre (SUMO's sub-lane model lets vehicles drift within, and
    # change, lanes), and never outside the lanes, at most half a lane width (3.2 m) from a centre line.
    assert len(distance) >= 300
    assert np.median(distance) < 0.3 and np.percentile(distance, 75) < 0.75 and distance.max() < 1.7


@pytest.fixture(scope="module")
def random_run() -> sumo_sim.SumoRun:
    try:
        return sumo.simulate_shard(("random",), 2, 2, COUNT)  # a network with turn pockets and one-ways
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))


@pytest.mark.parametrize("network", ["grid", "random"])
def test_logged_vehicles_are_on_the_road_side_of_every_edge(
    network: str, run: sumo_sim.SumoRun, random_run: sumo_sim.SumoRun
) -> None:
    """Road edges keep the road on their left (the off-road metric's convention), also medians (closed
    islands) and the left curbs of one-way roads, and each scene's map covers every valid agent: logged
    vehicles are on-road in the scenes cut from a run, and 8 m to their right mostly off-road."""
    from trajeglish_env.batch_geometry import road_edges
    from trajeglish_env.metrics.road_edges import distance_to_road_edge, signed_distance_to_road_edges

    simulated = run if network == "grid" else random_run
    on, inside, beyond = 0, [], []
    seed, shard = (SEED, SHARD) if network == "grid" else (2, 2)
    for scene in sumo.cut_scenes(simulated, seed, shard, COUNT):
        veh = np.flatnonzero(scene.kind == AgentKind.VEHICLE)
        valid = scene.valid[veh]
        xyz = np.concatenate([scene.xyh[veh, :, :2], np.zeros((*valid.shape, 1))], axis=-1)
        box = np.concatenate([scene.size[veh], np.full((len(veh), 1), 1.5)], axis=-1)[:, None]
        edges = road_edges(scene)
        corners = distance_to_road_edge(xyz, scene.xyh[veh, :, 2], box, valid, edges)[valid]
        on += valid.sum()
        inside.append(corners)
        heading = scene.xyh[veh][valid][:, 2]
        right = scene.xyh[veh][valid][:, :2] + 8.0 * np.stack([np.sin(heading), -np.cos(heading)], axis=1)
        beyond.append(signed_distance_to_road_edges(right, edges))
    inside_all, beyond_all = np.concatenate(inside), np.concatenate(beyond)
    assert on > 1000
    # box corners stay on the road (SUMO's junction turns may cut a corner by a few cm)
    assert np.mean(inside_all > 0.05) < 0.005 and inside_all.max() < 1.0, np.mean(inside_all > 0.05)
    assert np.mean(beyond_all > 0.0) > 0.5, np.mean(beyond_all > 0.0)


def test_vehicles_overlap_only_where_sumo_reports_a_collision(run: sumo_sim.SumoRun) -> None:
    rows = np.flatnonzero(np.isin(run.kind, [AgentKind.VEHICLE, AgentKind.CYCLIST]))
    overlaps = _overlaps(run.xyh[rows], run.size[rows], run.valid[rows], shrink=0.2)
    reported = {frozenset((a.split("#")[0], b.split("#")[0])) for _, a, b in run.collisions}
    names = [run.names[r].split("#")[0] for r in rows]
    unexplained = [(t, i, j) for t, i, j in overlaps if frozenset((names[i], names[j])) not in reported]
    # On lanes (off junctions) boxes never overlap unless SUMO reports a collision. Inside junctions SUMO's
    # model is not geometric (a long vehicle's rigid box cuts the corner of a turn): rare, tolerated.
    on_lanes = [
        (t, names[i], names[j]) for t, i, j in unexplained if not run.on_junction[rows[[i, j]], t].any()
    ]
    assert not on_lanes, f"vehicle boxes overlap on lanes without a SUMO collision: {on_lanes[:5]}"
    assert len(unexplained) <= 0.005 * run.valid[rows].sum()


def test_map_has_lanes_lines_edges_and_closed_crosswalks(scenes: list[Scenario]) -> None:
    for scene in scenes:
        kinds = {MapKind(k) for k in scene.map_kind}
        assert MapKind.LANE_SURFACE_STREET in kinds and MapKind.CROSSWALK in kinds
        assert kinds & ROAD_LINE_KINDS and kinds & ROAD_EDGE_KINDS
        assert len(np.unique(scene.map_id)) == scene.num_polylines
        for k in range(scene.num_polylines):
            line = scene.polyline(k)
            if scene.map_kind[k] == MapKind.CROSSWALK:
                assert len(line) == 5 and np.allclose(line[0], line[-1])
            else:
                assert np.linalg.norm(np.diff(line, axis=0), axis=1).max() <= 1.0 + 1e-9
        # the map holds what lies within 100 m of the sdc's path (its position every second)
        path = scene.xyh[scene.sdc, ::10, :2]
        nearest = np.array(
            [
                np.linalg.norm(scene.polyline(k)[:, None, :2] - path[None], axis=-1).min()
                for k in range(scene.num_polylines)
            ]
        )
        assert nearest.max() <= 100.0


def test_traffic_light_states_per_step(scenes: list[Scenario]) -> None:
    seen: set[int] = set()
    for scene in scenes:
        assert scene.signal_state is not None and scene.signal_state.shape == (91, len(scene.signal_lane_id))
        assert len(scene.signal_lane_id) > 0
        index = {int(i): k for k, i in enumerate(scene.map_id)}
        for lane_id, stop in zip(scene.signal_lane_id, scene.signal_xy, strict=True):
            k = index[int(lane_id)]  # every signal names a lane polyline of the scene's map
            assert scene.map_kind[k] in LANE_KINDS
            np.testing.assert_allclose(scene.polyline(k)[0], stop)  # stop point where the movement starts
        seen |= set(np.unique(scene.signal_state).tolist())
    assert {SignalState.GO, SignalState.STOP} <= seen and seen <= {int(s) for s in SignalState}
    assert SignalState.UNKNOWN not in seen


def test_scenes_round_trip_through_shard_files(scenes: list[Scenario], tmp_path: Path) -> None:
    path = save_scenarios(tmp_path / "sumo.scn.npz", scenes)
    assert all(a.equals(b) for a, b in zip(scenes, load_scenarios(path), strict=True))


def test_generation_is_deterministic_per_seed(scenes: list[Scenario]) -> None:
    again = sumo.generate_shard(KINDS, SEED, SHARD, COUNT)
    assert all(a.equals(b) for a, b in zip(scenes, again, strict=True))


# ---------------------------------------------------------------------------------------------- units
def test_fcd_angles_become_headings_ccw_from_x(tmp_path: Path) -> None:
    fcd = tmp_path / "fcd.csv"
    fcd.write_text(
        "timestep_time;vehicle_id;vehicle_x;vehicle_y;vehicle_angle;vehicle_type;vehicle_speed;vehicle_pos;"
        "vehicle_lane\n"
        "0.00;v0;10.000;0.000;90.000;car;10.00;5.0;e1_0\n"  # heading east, the whole car on lane e1_0
        "0.10;v0;11.000;0.000;90.000;car;10.00;0.5;:j0_0_0\n"
        "0.00;v1;0.000;5.000;0.000;car;0.00;3.0;e2_0\n"  # heading north, its back still off the lane
        "0.10;p0;3.000;4.000;180.000;ped;1.20;0.0;\n"  # heading south
    )
    net = SumoNet(
        lanes={
            "e1_0": Lane("e1_0", "e1", 0, np.array([[0.0, 0.0], [10.0, 0.0]]), 3.2, "drive", 10.0),
            "e2_0": Lane("e2_0", "e2", 0, np.array([[0.0, 0.0], [0.0, 10.0]]), 3.2, "drive", 10.0),
        },
        edges={},
        connections=(),
        next_internal={},
        tls_ids=(),
        fringe_nodes=frozenset(),
    )
    types = {"car": AgentType("car", "car", 4.0, 1.8), "ped": AgentType("ped", "ped", 0.5, 0.6)}
    tracks = sumo_sim._read_fcd([fcd], num_steps=2, types=types, net=net)
    assert tracks.names.tolist() == ["p0", "v0", "v1"]
    assert tracks.kind.tolist() == [AgentKind.PEDESTRIAN, AgentKind.VEHICLE, AgentKind.VEHICLE]
    np.testing.assert_allclose(tracks.xyh[1], [[10.0, 0.0, 0.0], [11.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(tracks.xyh[2, 0], [0.0, 5.0, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(tracks.xyh[0, 1], [3.0, 4.0, -np.pi / 2], atol=1e-12)
    assert tracks.valid.tolist() == [[False, True], [True, True], [True, False]]
    assert tracks.on_junction.tolist() == [
        [False, False],
        [False, True],
        [True, False],
    ]  # v1: back off the lane
    np.testing.assert_allclose(tracks.size[1], [4.0, 1.8])
    np.testing.assert_allclose(tracks.speed[1], [10.0, 10.0])
    assert tracks.lane_heading[1, 0] == pytest.approx(0.0)  # the lane's direction under the car
    assert np.isnan(tracks.lane_heading[[2, 1, 0], [0, 1, 1]]).all()  # partly on the lane, junction, sidewalk


def test_vehicle_boxes_sit_behind_the_front_bumper_and_cannot_turn_on_the_spot() -> None:
    config = sumo_sim.SimulationConfig(min_turn_radius_m=2.5, max_lane_deviation_rad=0.12)
    front = np.zeros((1, 4, 3))
    front[0, :, 0] = [10.0, 11.0, 11.0, 11.0]  # drives 1 m east, then stands
    front[0, :, 2] = [0.0, 0.0, 0.8, 0.0]  # SUMO rotates the standing car by 0.8 rad for one step
    speed, valid, no_lane = (
        np.array([[10.0, 10.0, 0.0, 0.0]]),
        np.ones((1, 4), dtype=bool),
        np.full((1, 4), np.nan),
    )
    boxes = sumo_sim.vehicle_boxes(front, speed, no_lane, valid, np.array([4.0]), config)
    np.testing.assert_allclose(boxes[0, :, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(boxes[0, :, :2], [[8.0, 0.0], [9.0, 0.0], [9.0, 0.0], [9.0, 0.0]], atol=1e-12)
    front[0, :, 0] = [0.0, 1.0, 2.0, 3.0]  # driving: a 0.3 rad turn over 1 m is within the steering limit
    front[0, :, 2] = [0.0, 0.3, 0.3, 0.3]
    boxes = sumo_sim.vehicle_boxes(front, np.full((1, 4), 10.0), no_lane, valid, np.array([4.0]), config)
    np.testing.assert_allclose(boxes[0, :, 2], [0.0, 0.3, 0.3, 0.3], atol=1e-12)
    # ... but on a lane heading east, the heading stays within 0.12 rad of the lane's direction.
    boxes = sumo_sim.vehicle_boxes(
        front, np.full((1, 4), 10.0), np.zeros((1, 4)), valid, np.array([4.0]), config
    )
    np.testing.assert_allclose(boxes[0, :, 2], [0.0, 0.12, 0.12, 0.12], atol=1e-12)


def test_offset_polyline_keeps_its_distance_around_corners() -> None:
    corner = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # east, then north (a left turn)
    left = sumo_map.offset_polyline(corner, 1.0)
    np.testing.assert_allclose(left, [[0.0, 1.0], [9.0, 1.0], [9.0, 10.0]], atol=1e-12)
    np.testing.assert_allclose(
        sumo_map.offset_polyline(corner, -1.0), [[0.0, -1.0], [11.0, -1.0], [11.0, 10.0]]
    )


def test_sumo_signal_characters_map_to_womd_states() -> None:
    states = sumo_map.signal_states(np.array(["GgyrsuoO", "rrrrrrrG"], dtype=object), np.array([0, 2, 3, 7]))
    go, caution, stop, unknown = SignalState.GO, SignalState.CAUTION, SignalState.STOP, SignalState.UNKNOWN
    assert states.tolist() == [[go, caution, stop, unknown], [stop, stop, stop, go]]


def test_teleports_and_gaps_split_tracks() -> None:
    xyh = np.zeros((1, 6, 3))
    xyh[0, :, 0] = [0.0, 1.0, 2.0, 50.0, 51.0, 0.0]  # jump between steps 2 and 3
    valid = np.array([[True, True, True, True, True, False]])
    out, out_valid, source = sumo_sim.split_tracks(xyh, valid, max_step_m=4.0)
    assert source.tolist() == [0, 0]
    assert out_valid.tolist() == [
        [True, True, True, False, False, False],
        [False, False, False, True, True, False],
    ]
    np.testing.assert_array_equal(out[1, 3:5, 0], [50.0, 51.0])


def test_pedestrian_hops_are_smoothed_away() -> None:
    steps = 40
    xyh = np.zeros((1, steps, 3))
    xyh[0, :, 0] = 0.12 * np.arange(steps)
    xyh[0, 20:, 1] = 0.8  # SUMO's sideways hop at a lane transition
    valid = np.ones((1, steps), dtype=bool)
    out = sumo_sim.smooth_pedestrians(xyh, valid, half=3, min_speed=0.3)
    speed = np.linalg.norm(np.diff(out[0, :, :2], axis=0), axis=1) / 0.1
    assert speed.max() < 2.5 and np.abs(out[0, :5, 2]).max() < 1e-9
    np.testing.assert_allclose(out[0, 25:35, :2], xyh[0, 25:35, :2], atol=1e-9)


def test_missing_sumo_gives_an_install_hint(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    with monkeypatch.context() as patch:  # binaries missing from the installation
        patch.setattr(sumo_tools, "sumo_home", lambda: tmp_path / "no-sumo")
        with pytest.raises(sumo.SumoNotAvailableError, match=r"pip install 'trajeglish_env\[sumo\]'"):
            sumo.generate_shard(KINDS, SEED, SHARD, 1)
    monkeypatch.setitem(sys.modules, "sumo", None)  # the eclipse-sumo package itself missing
    monkeypatch.delenv("SUMO_HOME", raising=False)
    with pytest.raises(sumo.SumoNotAvailableError, match="import sumo failed"):
        sumo.generate_shard(KINDS, SEED, SHARD, 1)
    # the CLI: one line, exit 2, and no output folder made before the check (it crashed with a traceback)
    from trajeglish_env.cli import main

    out = tmp_path / "scenes"
    assert main(["generate", "--source", "sumo", "--scenes", "2", "--out", str(out), "--quiet"]) == 2
    assert not out.exists()


def test_failing_tool_quotes_its_stderr(tmp_path: Path) -> None:
    try:
        sumo_tools.sumo_binary("netgenerate")
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))
    with pytest.raises(sumo.SumoToolError, match=r"netgenerate failed .*grid\.number"):
        sumo_tools.run_tool("netgenerate", ["--grid", "--grid.number=notanumber"], cwd=tmp_path)


def test_unknown_scene_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="expected a non-empty subset of"):
        sumo.generate_shard(("highway",), SEED, SHARD, 1)


def _lane_points_off_road(scenes: list[Scenario], reach: float = 50.0) -> tuple[int, int]:
    """Lane-centre points within ``reach`` m of an agent at the current step that the off-road rule
    signs beyond a road edge, and all such points, over ``scenes``."""
    from trajeglish_env.batch_geometry import road_edges
    from trajeglish_env.metrics.road_edges import signed_distance_to_road_edges

    off = total = 0
    for scene in scenes:
        lanes = [p[:, :2] for p in scene.polylines(frozenset({MapKind.LANE_SURFACE_STREET}))]
        points = np.concatenate(lanes)
        now = scene.xyh[scene.valid[:, scene.current_index], scene.current_index, :2]
        points = points[np.linalg.norm(points[:, None] - now[None], axis=-1).min(axis=1) < reach]
        off += int((signed_distance_to_road_edges(points, road_edges(scene)) > 0).sum())
        total += len(points)
    return off, total


def test_junctions_of_random_networks_are_on_the_road() -> None:
    """Curbs that turn a junction corner are chained into one polyline, curb stubs are left out and island
    rings start in the middle of a side, so no wedge of a junction is signed off the road: every lane
    centre near the agents is on the road side (before: 148 of these 19,958 points, 0.74 %, off the road,
    in wedges cast from the corners and spikes from the tips of islands)."""
    try:
        run = sumo.simulate_shard(("random",), 50050, 2, COUNT)  # the development scenes' networks
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))
    scenes = sumo.cut_scenes(run, 50050, 2, COUNT)
    assert sumo.GENERATOR_VERSION == 3  # directories of the maps before are not resumed into
    off, total = _lane_points_off_road(scenes)
    assert total > 15000
    assert off == 0, (off, total)
    for scene in scenes:
        for line in scene.polylines(ROAD_EDGE_KINDS):
            closed = len(line) > 2 and np.allclose(line[0], line[-1])
            assert closed or np.linalg.norm(np.diff(line[:, :2], axis=0), axis=1).sum() >= 1.0


def test_curbs_meeting_at_a_corner_are_chained_and_sign_the_junction_as_road() -> None:
    """A block's sharp corner (135 degrees) as two curbs 3 cm apart, the road on their left: apart, the
    first curb's end casts a wedge of "off the road" into the junction (its line, extended, signs the
    points nearer its end than the second curb's start); chained, every road point 0.5 m or more from the
    block is on the road side. A block whose four sides come as four curbs closes
    into one polyline without a backward step; an island's ring starts in the middle of a side; a curb stub
    is left out, a short lane is not."""
    from trajeglish_env.metrics.road_edges import RoadEdges, signed_distance_to_road_edges
    from trajeglish_env.sources.sumo_map import _MapBuilder, chain_road_edges

    north_west = np.stack([np.linspace(6.0, 0.0, 11), np.linspace(-6.0, 0.0, 11)], axis=1)  # to (0, 0)
    eastward = np.stack([np.linspace(0.03, 10.0, 11), np.full(11, -0.01)], axis=1)
    grid = np.stack(np.meshgrid(np.linspace(-8, 8, 81), np.linspace(-8, 8, 81)), -1).reshape(-1, 2)
    road = grid[(grid[:, 1] > 0.5) | (grid.sum(axis=1) < -0.75)]  # the block: y < 0 and x + y > 0
    kinds = [int(MapKind.ROAD_EDGE_BOUNDARY)] * 2
    apart = signed_distance_to_road_edges(road, RoadEdges.from_polylines([north_west, eastward]))
    lines, out_kinds, keep = chain_road_edges([north_west, eastward], kinds)
    joined = signed_distance_to_road_edges(road, RoadEdges.from_polylines(lines))
    assert (apart > 0).sum() > 50  # the wedge
    assert (joined < 0).all() and len(lines) == 1 and keep.tolist() == [True, False]
    assert out_kinds == kinds[:1] and len(lines[0]) == 21
    up = np.stack([np.zeros(11), np.linspace(-10.0, 0.0, 11)], axis=1)  # x = 0, northward
    east = np.stack([np.linspace(0.03, 10.0, 11), np.full(11, 0.02)], axis=1)  # y = 0, eastward
    square = [up, east, np.stack([np.full(11, 10.0), np.linspace(0.02, -10.0, 11)], 1)]
    square.append(np.stack([np.linspace(10.0, 0.0, 11), np.full(11, -10.03)], 1))
    lines, _, keep = chain_road_edges(square[::-1], kinds * 2)  # any order
    (ring,) = lines
    assert np.allclose(ring[0], ring[-1]) and len(ring) == 41 and keep.sum() == 1
    steps = np.diff(ring, axis=0)
    turns = np.einsum("ij,ij->i", steps[:-1], steps[1:])
    assert (turns >= 0).all()  # never a step back
    run = np.stack([np.linspace(0.0, 20.0, 21), np.zeros(21)], axis=1)
    island = sumo_map._sliver(run)  # a thin island: its ring starts and ends in the middle of its side
    assert np.allclose(island[0], run[10]) and np.allclose(island[-1], run[10]) and len(island) == 43
    builder = _MapBuilder(1.0)
    assert builder.add(np.array([[0.0, 0.0], [0.2, 0.1]]), MapKind.ROAD_EDGE_BOUNDARY) == -1
    assert builder.add(np.array([[0.0, 0.0], [0.2, 0.1]]), MapKind.LANE_SURFACE_STREET) == 0


HOOKED_KERB = (
    np.array(  # a spider network's acute block corner (seed 100): the corner's kerb starts with a hook
        [
            [131.83, 210.57],
            [131.04, 209.99],
            [130.25, 209.42],
            [129.46, 208.84],
            [128.67, 208.26],
            [129.57, 208.28],
        ]
        + [[129.93, 208.26], [129.74, 209.18], [129.61, 210.1], [129.5, 211.1]]
    )
)


def test_a_hooked_kerb_loses_its_hook_and_the_junction_beyond_is_road() -> None:
    """The hook winds the wrong way round the corner, which signed the junction beyond it 11.9 m "off the
    road" where logged vehicles drive; real bends (a 2 m island, a square corner) are kept."""
    from trajeglish_env.metrics.road_edges import RoadEdges, signed_distance_to_road_edges
    from trajeglish_env.sources.sumo_map import despike

    unhooked = despike(HOOKED_KERB)
    hook = HOOKED_KERB[4:7]
    assert not (unhooked[:, None] == hook[None]).all(-1).any()  # the hook's three points are gone
    assert len(unhooked) >= 5 and np.array_equal(unhooked[[0, -1]], HOOKED_KERB[[0, -1]])
    in_junction = np.array([[122.8, 197.9]])
    before = signed_distance_to_road_edges(in_junction, RoadEdges.from_polylines([HOOKED_KERB]))
    after = signed_distance_to_road_edges(in_junction, RoadEdges.from_polylines([unhooked]))
    assert before[0] > 10 and after[0] < 0
    angle = np.linspace(0, 2 * np.pi, 26)
    island = 2.0 * np.stack([np.cos(angle), np.sin(angle)], -1)
    corner = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]])
    assert np.array_equal(despike(island), island) and np.array_equal(despike(corner), corner)
    # the generator's own median islands and slivers turn exactly half a circle at their tips: kept, at any
    # orientation (a first version cut a third of them for rounding noise)
    from trajeglish_env.sources.sumo_map import _ring_from_middle, _sliver, offset_polyline

    rng = np.random.default_rng(0)
    for _ in range(200):
        heading, width = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 4.5)
        run = np.outer(np.linspace(0, rng.uniform(3, 25), 6), [np.cos(heading), np.sin(heading)])
        run += rng.uniform(-100, 100, 2)
        median = _ring_from_middle(np.concatenate([run, offset_polyline(run, -width)[::-1]]), len(run) // 2)
        for ring in (median, _sliver(run)):
            assert np.array_equal(despike(ring), ring)


def test_a_partial_shard_holds_the_first_scenes_of_the_full_one(tmp_path: Path) -> None:
    """`--scenes 3` gave scenes with the ids of `--scenes 8`'s first three but other content (the
    simulation's length followed the shard's scene count)."""
    short = sumo.generate_shard(("grid",), 0, 0, 2, capacity=4)
    full = sumo.generate_shard(("grid",), 0, 0, 4, capacity=4)
    assert [s.scenario_id for s in short] == [s.scenario_id for s in full[:2]]
    assert all(a.equals(b) for a, b in zip(short, full, strict=False))


def test_generate_reports_the_scenes_of_each_network_kind() -> None:
    """A SUMO shard is one network of one kind: a run of fewer shards than kinds lacks some, which
    ``generate`` reports (``kind_scenes``) and warns about, instead of listing every requested kind."""
    from trajeglish_env.sources import highway
    from trajeglish_env.sources.generation import GenerationConfig, _kind_scenes

    small = GenerationConfig("sumo", 6, 3, ("grid", "spider", "random"))
    counts = _kind_scenes(sumo, small)
    assert sum(counts.values()) == 6 and sorted(counts.values()) == [0, 0, 6]  # one shard, one kind
    spread = _kind_scenes(sumo, GenerationConfig("sumo", 6, 3, ("grid", "spider", "random"), 1))
    assert sum(spread.values()) == 6 and sum(v > 0 for v in spread.values()) >= 2
    assert _kind_scenes(highway, GenerationConfig("highway", 6, 3, ("merge",))) is None  # a kind per scene
