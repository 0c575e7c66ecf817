"""The highway-env scene source: valid, deterministic, physically consistent scenes and maps."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import RoadNetwork

from trajeglish_env.geometry import box_corners, wrap_angle
from trajeglish_env.scenario import LANE_KINDS, ROAD_EDGE_KINDS, ROAD_LINE_KINDS, AgentKind, MapKind, Scenario
from trajeglish_env.sources import highway
from trajeglish_env.sources.generation import scene_seed
from trajeglish_env.sources.highway import KINDS, HighwaySceneConfig, SceneCrashError, generate_scene
from trajeglish_env.sources.highway_map import network_polylines

STRAIGHT_ROAD_KINDS = ("highway", "exit", "two-way")


@functools.cache
def scene(kind: str, seed: int = 0) -> Scenario:
    """One generated scene per (kind, seed), shared by the tests of this file."""
    return generate_scene(kind, seed)


def _moving_states(sc: Scenario, min_speed: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centred-difference velocity direction, speed and yaw rate at steps whose neighbours are valid."""
    ok = sc.valid[:, :-2] & sc.valid[:, 1:-1] & sc.valid[:, 2:]
    d = sc.xyh[:, 2:, :2] - sc.xyh[:, :-2, :2]
    speed = np.linalg.norm(d, axis=-1) / (2 * sc.dt)
    yaw_rate = np.abs(wrap_angle(sc.xyh[:, 2:, 2] - sc.xyh[:, :-2, 2])) / (2 * sc.dt)
    mask = ok & (speed > min_speed)
    motion = np.arctan2(d[..., 1], d[..., 0])
    error = np.abs(wrap_angle(motion - sc.xyh[:, 1:-1, 2]))
    return error[mask], speed[mask], yaw_rate[mask]


def _segments(sc: Scenario, kinds: frozenset[MapKind]) -> tuple[np.ndarray, np.ndarray]:
    starts, ends = [], []
    for k in np.flatnonzero(np.isin(sc.map_kind, list(kinds))):
        p = sc.polyline(k)
        starts.append(p[:-1])
        ends.append(p[1:])
    return np.concatenate(starts), np.concatenate(ends)


def _boxes_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Separating-axis test for convex quadrilaterals ``[..., 4, 2]`` (True where they intersect)."""
    a, b = np.broadcast_arrays(a, b)
    overlap = np.ones(a.shape[:-2], dtype=bool)
    for box in (a, b):
        edges = np.roll(box, -1, axis=-2) - box
        axes = np.stack([-edges[..., 1], edges[..., 0]], -1)  # [..., 4, 2]
        pa = np.einsum("...kd,...jd->...kj", axes, a)
        pb = np.einsum("...kd,...jd->...kj", axes, b)
        separated = (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
        overlap &= ~separated.any(-1)
    return overlap


# ------------------------------------------------------------------------------------ scene shape
@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_builds_a_valid_scene(kind: str) -> None:
    sc = scene(kind)
    sc.validate()
    assert sc.num_steps == 91 and sc.current_index == 10 and sc.dt == pytest.approx(0.1)
    assert sc.source == "highway" and sc.scenario_id == f"highway-{kind}-0"
    assert sc.num_agents >= 2
    assert sc.valid[sc.sdc].all()
    assert (sc.kind == AgentKind.VEHICLE).all()
    np.testing.assert_array_equal(sc.size, np.tile([5.0, 2.0], (sc.num_agents, 1)))
    assert sc.valid.any(axis=1).all()  # no agent is never valid
    # validity is one contiguous run per agent: a vehicle appears once and leaves once
    assert (np.abs(np.diff(sc.valid.astype(np.int8), axis=1)).sum(axis=1) <= 2).all()
    assert sc.signal_state is None
    assert all(sc.valid[i].all() and i != sc.sdc for i in sc.tracks_to_predict)


@pytest.mark.parametrize("kind", KINDS)
def test_speeds_are_plausible(kind: str) -> None:
    sc = scene(kind)
    speed = sc.speed()[sc.valid]
    assert speed.min() >= 0.0 and speed.max() <= 45.0
    assert sc.speed()[sc.sdc].mean() > 2.0  # the ego drives


@pytest.mark.parametrize("kind", KINDS)
def test_heading_follows_the_motion(kind: str) -> None:
    """Heading matches the direction of motion up to the kinematic-bicycle slip angle.

    highway-env's box centre moves at slip angle beta off the heading, with sin(beta) = yaw_rate *
    (length / 2) / speed; a mirrored or offset frame would break this bound by tens of degrees.
    """
    error, speed, yaw_rate = _moving_states(scene(kind))
    assert len(error) > 100
    slip = np.arcsin(np.clip(yaw_rate * 2.5 / speed, 0.0, 1.0))
    assert (error <= slip + np.radians(3.0)).all()
    assert np.median(error) < np.radians(6.0)
    if kind in STRAIGHT_ROAD_KINDS:
        assert np.percentile(error, 99) < np.radians(2.0)


@pytest.mark.parametrize("kind", KINDS)
def test_vehicles_drive_on_lane_centres(kind: str) -> None:
    sc = scene(kind)
    centres = np.concatenate(sc.polylines(LANE_KINDS))
    points = sc.xyh[sc.valid][:, :2]
    nearest = np.sqrt(((points[:, None, :] - centres[None]) ** 2).sum(-1)).min(axis=1)
    assert np.mean(nearest < 1.0) > 0.9
    assert nearest.max() < 3.0  # mid lane change at worst


@pytest.mark.parametrize("kind", KINDS)
def test_no_vehicle_box_overlaps_the_ego(kind: str) -> None:
    sc = scene(kind)
    corners = box_corners(sc.xyh, sc.size[:, None, :])  # [N, T, 4, 2]
    hit = _boxes_overlap(corners, corners[sc.sdc][None]) & sc.valid & sc.valid[sc.sdc]
    hit[sc.sdc] = False
    assert not hit.any()


def test_box_overlap_helper_detects_overlap() -> None:
    a = box_corners(np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.3], [6.0, 0.0, 0.0]]), np.array([5.0, 2.0]))
    assert _boxes_overlap(a[:, None], a[None, :]).tolist() == [
        [True, True, False],
        [True, True, True],
        [False, True, True],
    ]


def test_roundabout_traffic_is_right_handed() -> None:
    """Right-hand traffic circulates counter-clockwise: positive angular momentum about the centre."""
    sc = scene("roundabout")
    pos = sc.xyh[:, 1:, :2]
    vel = np.diff(sc.xyh[..., :2], axis=1)
    radius = np.linalg.norm(pos, axis=-1)
    on_ring = sc.valid[:, 1:] & sc.valid[:, :-1] & (radius < 30.0) & (np.linalg.norm(vel, axis=-1) > 0.1)
    spin = pos[..., 0] * vel[..., 1] - pos[..., 1] * vel[..., 0]
    assert on_ring.sum() > 50
    assert np.mean(spin[on_ring] > 0) > 0.95


def test_two_way_oncoming_traffic_keeps_right() -> None:
    """Eastbound cars drive south (right) of westbound ones."""
    sc = scene("two-way")
    heading, y = sc.xyh[..., 2][sc.valid], sc.xyh[..., 1][sc.valid]
    east, west = np.abs(heading) < 0.3, np.abs(heading) > np.pi - 0.3
    assert east.sum() and west.sum()
    assert y[east].max() < y[west].min()


# ------------------------------------------------------------------------------------ the map
@pytest.mark.parametrize("kind", KINDS)
def test_map_has_lanes_lines_and_edges_finely_sampled(kind: str) -> None:
    sc = scene(kind)
    expected_lane = (
        MapKind.LANE_FREEWAY if kind in ("highway", "merge", "exit") else MapKind.LANE_SURFACE_STREET
    )
    assert (sc.map_kind == expected_lane).any()
    assert set(sc.map_kind.tolist()) <= {int(expected_lane)} | {
        int(k) for k in ROAD_LINE_KINDS | ROAD_EDGE_KINDS
    }
    assert np.isin(sc.map_kind, list(ROAD_LINE_KINDS)).any()
    assert (sc.map_kind == MapKind.ROAD_EDGE_BOUNDARY).any()
    starts, ends = _segments(sc, frozenset(MapKind))
    spacing = np.linalg.norm(ends - starts, axis=-1)
    assert spacing.max() <= 0.5 + 1e-9 and spacing.min() > 0.05
    assert len(np.unique(sc.map_id)) == sc.num_polylines


@pytest.mark.parametrize("kind", KINDS)
def test_road_edges_bound_the_traffic(kind: str) -> None:
    """No vehicle centre comes near a road edge, and edges keep the road on their left (WOSAC winding)."""
    sc = scene(kind)
    a, b = _segments(sc, ROAD_EDGE_KINDS)
    points = sc.xyh[sc.valid][:, :2]
    ab = b - a
    t = ((points[:, None] - a[None]) * ab[None]).sum(-1) / (ab**2).sum(-1)[None]
    proj = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    dist = np.linalg.norm(points[:, None] - proj, axis=-1)
    j = dist.argmin(axis=1)
    assert dist.min() > 0.5  # highway-env's lane-following cuts roundabout exits by up to ~0.5 m
    inner = (t[np.arange(len(points)), j] > 0.0) & (t[np.arange(len(points)), j] < 1.0)
    side = ab[j, 0] * (points[:, 1] - a[j, 1]) - ab[j, 1] * (points[:, 0] - a[j, 0])
    assert inner.sum() > 0.5 * len(points)
    assert (side[inner] > 0).all()


def test_network_polylines_of_a_straight_three_lane_road() -> None:
    """Lines: solid, broken (painted by two lanes, kept once), broken, solid; edges on the outer sides."""
    net = RoadNetwork.straight_road_network(lanes=3, length=100.0)
    region = (np.array([-10.0, -50.0]), np.array([60.0, 50.0]))
    out = network_polylines(net, MapKind.LANE_FREEWAY, region, spacing=0.5)
    kinds = np.array(out.kinds)
    centre_y = sorted(
        float(p[0, 1]) for p, k in zip(out.polylines, kinds, strict=True) if k == MapKind.LANE_FREEWAY
    )
    assert centre_y == [-8.0, -4.0, 0.0]  # highway-env lanes at y = 0, 4, 8, mirrored
    lines = {float(p[0, 1]): k for p, k in zip(out.polylines, kinds, strict=True) if k in ROAD_LINE_KINDS}
    assert lines == {
        2.0: MapKind.ROAD_LINE_SOLID_SINGLE_WHITE,
        -2.0: MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE,
        -6.0: MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE,
        -10.0: MapKind.ROAD_LINE_SOLID_SINGLE_WHITE,
    }
    edges = [p for p, k in zip(out.polylines, kinds, strict=True) if k == MapKind.ROAD_EDGE_BOUNDARY]
    assert sorted(float(p[0, 1]) for p in edges) == [-10.0, 2.0]
    for p in edges:  # cropped to the region, road on the left
        assert p[:, 0].min() == pytest.approx(0.0) and p[:, 0].max() == pytest.approx(60.0, abs=0.3)
        heading_east = p[-1, 0] > p[0, 0]
        assert heading_east == (p[0, 1] < 0)


def test_lone_lane_with_striped_sides_gets_edges_on_both_sides() -> None:
    net = RoadNetwork()
    net.add_lane("a", "b", StraightLane([0, 0], [50, 0], line_types=(LineType.STRIPED, LineType.NONE)))
    out = network_polylines(
        net, MapKind.LANE_SURFACE_STREET, (np.array([-99.0, -99.0]), np.array([99.0, 99.0]))
    )
    assert sorted(out.kinds) == sorted(
        [MapKind.LANE_SURFACE_STREET, MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE, MapKind.ROAD_EDGE_BOUNDARY]
    )


# ------------------------------------------------------------------------------------ determinism
def test_same_seed_gives_bit_identical_scenes() -> None:
    first = scene("intersection")
    generate_scene("roundabout", 3)  # other work in between must not leak into the next scene
    again = generate_scene("intersection", 0)
    assert first.equals(again)


def test_different_seeds_give_different_scenes() -> None:
    a, b = scene("highway", 0), scene("highway", 1)
    assert not a.equals(b)
    assert a.xyh.shape != b.xyh.shape or not np.array_equal(a.xyh, b.xyh)


def test_intersection_vehicles_appear_over_time() -> None:
    sc = scene("intersection")
    first_valid = sc.valid.argmax(axis=1)
    assert (first_valid > 0).any()  # spawned during the recording


def test_ego_crash_is_retried_then_reported() -> None:
    # u-turn seed 0: the first attempts end in a crash (highway-env 1.12); retries find a clean scene.
    assert scene("u-turn").valid[scene("u-turn").sdc].all()
    with pytest.raises(SceneCrashError, match="'u-turn' seed 0: a vehicle crashed in all 1 attempts"):
        generate_scene("u-turn", 0, HighwaySceneConfig(max_attempts=1))


def test_generate_shard_is_deterministic_and_uses_scene_seeds() -> None:
    kinds = ("two-way", "merge")
    shard = highway.generate_shard(kinds, 7, 3, 2)
    assert len(shard) == 2
    assert all(a.equals(b) for a, b in zip(shard, highway.generate_shard(kinds, 7, 3, 2), strict=True))
    for slot, sc in enumerate(shard):
        seed = scene_seed(7, 3, slot)
        assert sc.scenario_id == f"highway-{kinds[seed % 2]}-{seed}"
    assert highway.generate_shard(kinds, 7, 3, 0) == []


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match="unknown highway scene kind 'parking'"):
        generate_scene("parking", 0)
    with pytest.raises(ValueError, match="unknown highway scene kind 'parking'"):
        highway.generate_shard(("highway", "parking"), 0, 0, 1)
    with pytest.raises(ValueError, match="seed must be a non-negative integer"):
        generate_scene("highway", -1)
    with pytest.raises(ValueError, match="HighwaySceneConfig.current_index"):
        HighwaySceneConfig(steps=10, current_index=10)


def test_two_way_traffic_keeps_its_lanes() -> None:
    """In every two-way scene the sdc overtook into the lane of the oncoming traffic (MOBIL does not see
    it) and drove the whole 9 s head-on at oncoming cars: no vehicle changes lanes there now."""
    for seed in (100, 101, 102, 103):
        sc = generate_scene("two-way", seed)
        for i in range(sc.num_agents):
            xyh = sc.xyh[i, sc.valid[i]]
            ahead = np.cos(xyh[:, 2]) > 0  # driving the forward way: the right lane (y = -4); else y = 0
            lane_y = np.where(ahead, -4.0, 0.0)
            assert np.abs(xyh[:, 1] - lane_y).max() < 0.5, (seed, i)


def test_the_bundled_two_way_scenes_keep_their_lanes() -> None:
    """The shipped bundle (the envs' default scenes) held two two-way scenes of the old generator, whose
    sdc drove in the oncoming lane: an ego following its route learned to."""
    from trajeglish_env.env.scenes import load_bundle

    bundle = load_bundle()
    two_way = [bundle.get(k) for k in range(len(bundle)) if "two-way" in bundle.get(k).scenario_id]
    assert len(two_way) == 2
    for sc in two_way:
        assert np.abs(sc.xyh[sc.sdc, sc.valid[sc.sdc], 1] + 4.0).max() < 0.5
