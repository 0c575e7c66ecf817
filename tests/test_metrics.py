"""Realism metrics on hand-built inputs with known answers: geometry, features, estimators, scores."""

from __future__ import annotations

import numpy as np
import pytest

from trajeglish_env.metrics import (
    CONFIGS,
    RoadEdges,
    average_displacement_errors,
    box_collisions,
    box_signed_distance,
    distance_to_road_edge,
    interaction_features,
    kinematic_features,
    mean_scores,
    min_average_displacement_error,
    score_rollouts,
    signed_distance_to_road_edges,
)
from trajeglish_env.metrics.likelihood import (
    bernoulli_log_likelihood,
    bin_index,
    histogram_edges,
    histogram_log_likelihood,
)
from trajeglish_env.metrics.road_edges import _nearest_exhaustive, _signed_distance_to
from trajeglish_env.metrics.traffic_lights import (
    TrafficSignals,
    _current_lane,
    _lane_metric,
    red_light_violations,
)
from trajeglish_env.scenario import AgentKind, MapKind, Scenario, SignalState

ROAD_HALF_WIDTH = 5.0


def _straight_edges(length: float = 400.0) -> list[np.ndarray]:
    """The two edges of a 10 m wide road along +x, road on their left (sampled every 0.5 m)."""
    xs = np.arange(-100.0, length, 0.5)
    right = np.stack([xs, np.full_like(xs, -ROAD_HALF_WIDTH)], -1)  # driving +x, road on the left
    left = np.stack([xs[::-1], np.full_like(xs, ROAD_HALF_WIDTH)], -1)
    return [right, left]


def _busy_scene(num_agents: int = 8, steps: int = 91, seed: int = 0) -> Scenario:
    """Vehicles on the 10 m road, speeding up, slowing down and weaving (not constant velocity)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * 0.1
    base = rng.uniform(8.5, 9.5, num_agents)  # similar speeds: nobody catches up with the car ahead
    wobble = rng.uniform(1.0, 3.0, num_agents)
    x = np.arange(num_agents)[:, None] * 15.0 + base[:, None] * t + wobble[:, None] * np.sin(0.8 * t)
    lane = np.where(np.arange(num_agents) % 2 == 0, -2.0, 2.0)
    y = lane[:, None] + 0.6 * np.sin(0.5 * t + np.arange(num_agents)[:, None])
    heading = np.arctan2(np.gradient(y, axis=1), np.gradient(x, axis=1))
    return Scenario.from_arrays(
        np.stack([x, y, heading], -1),
        np.ones((num_agents, steps), dtype=bool),
        np.tile([4.5, 2.0], (num_agents, 1)),
        np.full(num_agents, AgentKind.VEHICLE),
        track_id=np.arange(num_agents) + 10,
        polylines=_straight_edges(),
        polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY] * 2,
        scenario_id="busy",
        source="test",
    )


def _log_future(scene: Scenario) -> np.ndarray:
    return scene.xyh[:, scene.current_index + 1 :]


# ----------------------------------------------------------------------------------------- box geometry
def test_overlapping_boxes_collide_and_touching_ones_do_not():
    unit = np.array([2.0, 2.0])
    origin = np.array([0.0, 0.0, 0.0])
    assert box_collisions(origin, unit, np.array([1.5, 0.0, 0.0]), unit)
    assert box_collisions(origin, unit, np.array([1.0, 1.0, np.pi / 4]), unit, corner_rounding=0.7)
    # Corners touching at (1, 1), and edges touching along x = 1: distance exactly 0, no collision.
    assert not box_collisions(origin, unit, np.array([2.0, 2.0, 0.0]), unit)
    assert not box_collisions(origin, unit, np.array([2.0, 0.5, 0.0]), unit)
    assert box_signed_distance(origin, unit, np.array([2.0, 2.0, 0.0]), unit) == pytest.approx(0.0, abs=1e-12)
    # Rounded corners pull touching corners apart: cores 0.6 x 0.6, radii 0.7 each.
    rounded = box_signed_distance(origin, unit, np.array([2.0, 2.0, 0.0]), unit, corner_rounding=0.7)
    assert rounded == pytest.approx(1.4 * np.sqrt(2) - 1.4, abs=1e-9)


def _random_box_pairs(seed: int, n: int, spread: float) -> tuple[np.ndarray, ...]:
    """``n`` pairs of boxes: A near the origin, B within ``spread`` m, random headings and sizes."""
    rng = np.random.default_rng(seed)
    xyh_a = np.column_stack([rng.uniform(-1, 1, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    xyh_b = np.column_stack([rng.uniform(-spread, spread, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    return xyh_a, rng.uniform(0.5, 5.0, (n, 2)), xyh_b, rng.uniform(0.5, 5.0, (n, 2))


def test_sharp_box_collisions_are_exactly_negative_signed_distances():
    # the separating-axis shortcut of sharp boxes must flag exactly the pairs whose distance is negative,
    # including touching and nearly touching pairs
    xyh_a, size_a, xyh_b, size_b = _random_box_pairs(11, 20_000, 6.0)
    xyh_a[:100], xyh_b[:100] = [0.0, 0.0, 0.0], [4.0, 0.0, 0.0]  # touching end to end (distance 0)
    size_a[:100] = size_b[:100] = [4.0, 2.0]
    hit = box_collisions(xyh_a, size_a, xyh_b, size_b)
    assert np.array_equal(hit, box_signed_distance(xyh_a, size_a, xyh_b, size_b) < 0)
    assert 0.1 < hit.mean() < 0.9 and not hit[:100].any()


def test_box_signed_distance_known_values():
    box = np.array([4.0, 2.0])
    a = np.array([0.0, 0.0, 0.0])
    assert box_signed_distance(a, box, np.array([7.0, 0.0, 0.0]), box) == pytest.approx(3.0)
    assert box_signed_distance(a, box, np.array([3.0, 0.0, 0.0]), box) == pytest.approx(-1.0)  # 1 m overlap
    assert box_signed_distance(a, box, np.array([0.0, 1.5, 0.0]), box) == pytest.approx(-0.5)
    # A box rotated by 90 degrees beside the first: its long side is now along y.
    assert box_signed_distance(a, box, np.array([5.0, 0.0, np.pi / 2]), box) == pytest.approx(2.0)
    # Diagonal offset: corner (2, 1) to corner (4, 3).
    assert box_signed_distance(a, box, np.array([6.0, 4.0, 0.0]), box) == pytest.approx(np.sqrt(8.0))


def test_box_distance_matches_dense_boundary_sampling():
    xyh_a, size_a, xyh_b, size_b = _random_box_pairs(3, 100, 8.0)
    got = box_signed_distance(xyh_a, size_a, xyh_b, size_b)
    u = np.linspace(-0.5, 0.5, 101)
    unit = np.concatenate([np.stack([u, np.full_like(u, s)], -1) for s in (-0.5, 0.5)])
    unit = np.concatenate([unit, unit[:, ::-1]])  # 404 points on the unit square's boundary

    def boundary(xyh: np.ndarray, size: np.ndarray) -> np.ndarray:
        local = unit * size
        c, s = np.cos(xyh[2]), np.sin(xyh[2])
        return np.stack(
            [xyh[0] + c * local[:, 0] - s * local[:, 1], xyh[1] + s * local[:, 0] + c * local[:, 1]], -1
        )

    sampled = np.array(
        [
            np.linalg.norm(
                boundary(xyh_a[i], size_a[i])[:, None] - boundary(xyh_b[i], size_b[i])[None], axis=-1
            ).min()
            for i in range(len(xyh_a))
        ]
    )
    apart = got > 0
    assert apart.sum() > 50 and (~apart).sum() > 5
    np.testing.assert_allclose(got[apart], sampled[apart], atol=0.05)
    # Overlapping boxes: the two outlines cross or one holds the other, and the distance is negative.
    assert (sampled[~apart] < 0.05).all()
    assert (got == box_signed_distance(xyh_b, size_b, xyh_a, size_a)).mean() > 0.9  # symmetric


# ------------------------------------------------------------------------------------------- road edges
def test_lane_centre_is_on_road_and_5m_past_the_edge_is_off_road():
    edges = RoadEdges.from_polylines(_straight_edges())
    box = np.array([4.5, 2.0, 0.0])
    xyz = np.array(
        [[50.0, 0.0, 0.0], [50.0, ROAD_HALF_WIDTH + 5.0, 0.0], [50.0, -ROAD_HALF_WIDTH - 5.0, 0.0]]
    )
    distance = distance_to_road_edge(xyz, np.zeros(3), box, np.ones(3, bool), edges)
    # Centre line: the outermost corners are 1 m from the centre, 4 m inside the edge.
    np.testing.assert_allclose(distance, [-4.0, 6.0, 6.0], atol=1e-4)
    assert distance[0] < 0 < distance[1]
    invalid = distance_to_road_edge(xyz, np.zeros(3), box, np.zeros(3, bool), edges)
    assert (invalid == -1e10).all()


def test_road_edge_sign_at_polygon_corners_uses_convexity():
    # A counter-clockwise 20 m square: the road is inside; a closed polyline (ends coincide).
    square = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0], [0.0, 0.0]])
    edges = RoadEdges.from_polylines([square])
    points = np.array([[25.0, 25.0], [-3.0, -4.0], [10.0, 10.0], [19.0, 1.0], [20.0, 10.0]])
    got = signed_distance_to_road_edges(points, edges)
    np.testing.assert_allclose(got, [np.sqrt(50.0), 5.0, -10.0, -1.0, 0.0], atol=1e-5)


def test_grid_search_equals_exhaustive_search():
    rng = np.random.default_rng(7)
    lines = []
    for _ in range(12):  # wiggly 3-D polylines with uneven spacing, including long segments
        n = int(rng.integers(2, 60))
        steps = rng.normal(0, 1, (n, 2)) * rng.choice([0.3, 3.0, 25.0], (n, 1))
        start = rng.uniform(-150, 150, 2)
        xy = start + np.cumsum(steps, axis=0)
        lines.append(np.column_stack([xy, rng.normal(0, 0.5, n).cumsum() * 0.2]))
    edges = RoadEdges.from_polylines(lines)
    points = np.concatenate(
        [
            np.column_stack([rng.uniform(-200, 200, (3000, 2)), rng.normal(0, 1.0, 3000)]),
            np.column_stack([rng.uniform(-2000, 2000, (200, 2)), rng.normal(0, 30.0, 200)]),  # far, high
        ]
    ).astype(np.float32)
    got = signed_distance_to_road_edges(points, edges)
    expected = _signed_distance_to(edges, points, _nearest_exhaustive(edges, points, flat=False))
    np.testing.assert_array_equal(got, expected)
    planar = points.copy()
    planar[:, 2] = 0
    flat_edges = RoadEdges.from_polylines([line[:, :2] for line in lines])
    got = signed_distance_to_road_edges(planar, flat_edges)
    expected = _signed_distance_to(flat_edges, planar, _nearest_exhaustive(flat_edges, planar, flat=True))
    np.testing.assert_array_equal(got, expected)


# ------------------------------------------------------------------------------------ other features
def test_kinematics_of_a_constant_velocity_straight_line():
    t = np.arange(20) * 0.1
    xyz = np.stack([3.0 * t, 4.0 * t, np.zeros_like(t)], -1)[None]
    features = kinematic_features(xyz, np.full((1, 20), 0.3), 0.1)
    np.testing.assert_allclose(features["linear_speed"][0, 1:-1], 5.0, rtol=1e-5)
    np.testing.assert_allclose(features["linear_acceleration"][0, 2:-2], 0.0, atol=1e-3)
    np.testing.assert_allclose(features["angular_speed"][0, 1:-1], 0.0, atol=1e-6)
    assert np.isnan(features["linear_speed"][0, [0, -1]]).all()
    assert np.isnan(features["angular_acceleration"][0, [0, 1, -2, -1]]).all()
    # Headings crossing +-pi are wrapped: a slow left turn through pi.
    heading = np.mod(np.pi - 0.05 + 0.01 * np.arange(20) + np.pi, 2 * np.pi) - np.pi  # jumps pi -> -pi
    np.testing.assert_allclose(
        kinematic_features(xyz, heading[None], 0.1)["angular_speed"][0, 1:-1], 0.1, atol=1e-4
    )


def test_time_to_collision_and_nearest_object_known_values():
    # Ego at x = 0 doing 10 m/s, a lead 20 m ahead doing 5 m/s, and a car in the next lane.
    xy = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 4.0]])[None, :, None, :]
    speed = np.array([10.0, 5.0, 10.0])[None, :, None]
    size = np.tile([4.0, 2.0], (3, 1))
    ones = np.ones((1, 3, 1))
    features = interaction_features(xy, 0 * ones, ones.astype(bool), size, speed, np.array([0, 1]))
    # Gap 20 - 2 - 2 = 16 m closing at 5 m/s; the lead follows nobody.
    np.testing.assert_allclose(features.time_to_collision[0, :, 0], [3.2, 5.0], rtol=1e-5)
    # Nearest object of the ego: the neighbour, 2 m apart edge to edge, minus the rounding radii
    # (both 0.7 m) plus the cores' own gap: cores are 2.6 x 0.6, 3.4 m apart across -> 3.4 - 1.4 = 2.0.
    np.testing.assert_allclose(features.distance_to_nearest_object[0, 0, 0], 2.0, rtol=1e-5)
    assert not features.collision.any()


def _signals(state: int) -> TrafficSignals:
    lane = np.stack([np.arange(0.0, 100.0, 1.0), np.zeros(100)], -1)
    return TrafficSignals.build(
        [lane], [7], np.array([7]), np.full((5, 1), state), np.tile([[[50.0, 0.0]]], (5, 1, 1))
    )


@pytest.mark.parametrize(
    ("state", "violates"),
    [
        (SignalState.STOP, True),
        (SignalState.ARROW_STOP, True),
        (SignalState.GO, False),
        (SignalState.FLASHING_STOP, False),
    ],
)
def test_red_light_violation_when_crossing_the_stop_line(state, violates):
    x = np.array([47.0, 48.5, 49.5, 50.5, 52.0])  # crosses x = 50 between steps 2 and 3
    xy = np.stack([x, np.full(5, 0.2)], -1)[None, None]
    flags = red_light_violations(_signals(int(state)), xy, np.ones((1, 1, 5), bool), first_step=0)
    assert flags.tolist() == [[[False, False, violates, False]]]


def test_ade_and_min_ade_known_values():
    log = np.zeros((2, 4, 3))
    valid = np.array([[True, True, True, True], [True, True, False, False]])
    rollouts = np.zeros((2, 2, 4, 3))
    rollouts[0, 0, :, 0] = 1.0  # 1 m off at every step
    rollouts[0, 1, 2:, 1] = 9.0  # off only where the log is invalid: no error
    rollouts[1, 1, :, 2] = 2.0  # 2 m off (vertically) at every step
    ade = average_displacement_errors(rollouts, log, valid)
    np.testing.assert_allclose(ade, [[1.0, 0.0], [0.0, 2.0]])
    assert min_average_displacement_error(ade) == pytest.approx(0.5)  # best joint rollout, not per agent


def test_current_lane_search_equals_the_exhaustive_ranking_with_phantom_segments():
    rng = np.random.default_rng(5)
    lanes = []
    for _ in range(25):  # lanes of 2..40 points; the shorter ones get a phantom segment to (0, 0)
        n = int(rng.integers(2, 41))
        lanes.append(rng.uniform(-60, 60, 2) + np.cumsum(rng.normal(0, 2.0, (n, 2)), axis=0))
    signals = TrafficSignals.build(
        lanes, list(range(100, 125)), np.zeros(0), np.zeros((1, 0)), np.zeros((1, 0, 2))
    )
    q = rng.uniform(-80, 80, (500, 2)).astype(np.float32)
    start, end, usable = signals.segments()
    owner = np.broadcast_to(np.arange(len(start))[:, None], usable.shape)[usable]
    ranks = _lane_metric(q[:, None, :], start[usable][None], end[usable][None])
    expected = signals.lane_id[owner[np.argmin(ranks, axis=1)]]
    got = _current_lane(signals, q, rng.integers(0, len(lanes), len(q)))
    np.testing.assert_array_equal(got, expected)
    # The phantom segments (towards the origin) win for some points: the quirk is reproduced.
    phantom = np.zeros(usable.shape, bool)
    short = signals.num_points < signals.points.shape[1]
    phantom[short, signals.num_points[short] - 1] = True
    assert phantom[usable][np.argmin(ranks, axis=1)].any()


# ------------------------------------------------------------------------------------------- estimators
def test_histogram_binning_clips_and_sends_nan_to_the_top_bin():
    est = CONFIGS["2025"].linear_speed.estimator  # [0, 25], 10 bins
    assert histogram_edges(est)[[0, 1, -1]].tolist() == [0.0, 2.5, 25.0]
    got = bin_index(np.array([-3.0, 0.0, 2.49, 2.5, 24.99, 25.0, 99.0, np.nan]), est)
    assert got.tolist() == [0, 0, 0, 1, 9, 9, 9, 9]
    # One object, 2 rollouts x 2 steps in bin 0 and 1: P(bin 0) = (2 + 0.1) / (4 + 1).
    ll = histogram_log_likelihood(np.array([[1.0, 3.0, 20.0]]), np.array([[[1.0, 1.5]], [[3.0, 3.5]]]), est)
    np.testing.assert_allclose(np.exp(ll), [[2.1 / 5, 2.1 / 5, 0.1 / 5]])


def test_bernoulli_pseudocount_matches_the_reference():
    est = CONFIGS["2025"].collision_indication.estimator
    ll = bernoulli_log_likelihood(np.array([False, True]), np.zeros((32, 2), bool), est)
    np.testing.assert_allclose(np.exp(ll), [32.001 / 32.002, 0.001 / 32.002])


# ---------------------------------------------------------------------------------------------- scores
def test_the_log_scores_highest_and_constant_velocity_lower():
    scene = _busy_scene()
    future = _log_future(scene)
    log = score_rollouts(scene, np.repeat(future[None], 4, 0), scene.track_id, "2025")
    last = scene.xyh[:, scene.current_index]
    velocity = (last - scene.xyh[:, scene.current_index - 1])[:, :2] / scene.dt
    steps = np.arange(1, future.shape[1] + 1) * scene.dt
    cv = np.concatenate(
        [
            last[:, None, :2] + velocity[:, None] * steps[None, :, None],
            np.repeat(last[:, None, 2:], len(steps), 1),
        ],
        -1,
    )
    constant = score_rollouts(scene, np.repeat(cv[None], 4, 0), scene.track_id, "2025")
    rng = np.random.default_rng(1)
    noisy = future[None] + np.cumsum(rng.normal(0, [0.1, 0.1, 0.02], (4, *future.shape)), axis=2)
    jittered = score_rollouts(scene, noisy, scene.track_id, "2025")
    assert log.ade == 0.0 and log.min_ade == 0.0
    assert log.metametric > jittered.metametric and log.metametric > constant.metametric
    assert log.kinematic > constant.kinematic
    assert constant.ade > 0.5
    assert log.collision_rate == 0.0 and log.offroad_rate == 0.0
    both = mean_scores([log, constant])
    assert both.metametric == pytest.approx((log.metametric + constant.metametric) / 2)
    # counts are totals over the scenes (4 + 4 rollouts), and the mean's label says so
    assert both.num_rollouts == 8 and both.num_evaluated == log.num_evaluated + constant.num_evaluated
    assert both.scenario_id == "mean of 2 scenes (num_rollouts, num_evaluated: totals over them)"
    assert set(log.to_dict()) >= {"metametric", "kinematic", "interactive", "map_based", "min_ade"}


def test_the_2024_config_weighs_road_edges_more_and_ignores_red_lights():
    scene = _busy_scene()
    rollouts = np.repeat(_log_future(scene)[None], 2, 0)
    s24 = score_rollouts(scene, rollouts, scene.track_id, "2024")
    s25 = score_rollouts(scene, rollouts, scene.track_id, "2025")
    assert s24.feature_scores() == s25.feature_scores()
    expected = sum(CONFIGS["2024"].feature(f).weight * v for f, v in s24.feature_scores().items())
    assert s24.metametric == pytest.approx(expected)
    assert s24.metametric != pytest.approx(s25.metametric)


# -------------------------------------------------------------------------------------------- bad input
def test_bad_rollouts_are_rejected_clearly():
    scene = _busy_scene()
    good = np.repeat(_log_future(scene)[None], 2, 0)
    with pytest.raises(ValueError, match=r"the rollouts hold 40 future steps; WOSAC scores 80"):
        score_rollouts(scene, good[:, :, :40], scene.track_id)
    with pytest.raises(
        ValueError, match=r"rollouts_xyh must be \[R, 8 simulated agents, 80 future steps, 3\]"
    ):
        score_rollouts(scene, good[:, :7], scene.track_id)
    last = int(scene.track_id[-1])
    with pytest.raises(
        ValueError,
        match=rf"its 8 simulated agents .* hold 8: missing object id\(s\) \[{last}\], not simulated \[999",
    ):
        score_rollouts(scene, good, np.append(scene.track_id[:-1], 999))
    with pytest.raises(ValueError, match=rf"missing object id\(s\) \[{last}\], not simulated \[\]"):
        score_rollouts(scene, good[:, :7], scene.track_id[:-1])
    with pytest.raises(ValueError, match=r"appear more than once"):
        score_rollouts(scene, good, np.append(scene.track_id, scene.track_id[0]))
    bad = good.copy()
    bad[1, 3, 5, 0] = np.nan
    with pytest.raises(ValueError, match="rollout 1, object 13: non-finite"):
        score_rollouts(scene, bad, scene.track_id)
    with pytest.raises(ValueError, match="unknown metrics config"):
        score_rollouts(scene, good, scene.track_id, "2031")
    with pytest.raises(ValueError, match="rollouts_z must be"):
        score_rollouts(scene, good, scene.track_id, rollouts_z=np.zeros((2, 8, 3)))


def test_agent_order_of_the_rollouts_does_not_matter():
    scene = _busy_scene()
    rng = np.random.default_rng(2)
    rollouts = _log_future(scene)[None] + rng.normal(0, 0.3, (3, *_log_future(scene).shape))
    order = rng.permutation(scene.num_agents)
    a = score_rollouts(scene, rollouts, scene.track_id)
    b = score_rollouts(scene, rollouts[:, order], scene.track_id[order])
    assert a.to_dict() == b.to_dict()


def test_a_scene_without_road_edges_is_rejected():
    scene = _busy_scene()
    bare = Scenario.from_arrays(
        scene.xyh, scene.valid, scene.size, scene.kind, track_id=scene.track_id, scenario_id="bare"
    )
    with pytest.raises(ValueError, match="scenario 'bare': the scene has no road edge"):
        score_rollouts(bare, np.repeat(_log_future(scene)[None], 2, 0), scene.track_id)


def _brute_force_interactions(xy, heading, valid, size, speed, ev):
    """All-pairs reference of the nearest-object distance and TTC (no pruning), for one step."""
    xyh = np.concatenate([xy, heading[:, None]], -1).astype(np.float64)
    d = box_signed_distance(xyh[ev][:, None], size[ev][:, None], xyh[None], size[None], corner_rounding=0.7)
    d[np.arange(len(ev)), ev] = np.inf
    d[~(valid[ev][:, None] & valid[None])] = np.inf
    nearest = np.where(np.isinf(d.min(1)), 1e10, d.min(1))
    yaw = np.abs(heading[None] - heading[ev][:, None])
    c, s = np.abs(np.cos(yaw)), np.abs(np.sin(yaw))
    off = xy[None] - xy[ev][:, None]
    ce, se = np.cos(heading[ev])[:, None], np.sin(heading[ev])[:, None]
    gap = (
        ce * off[..., 0]
        + se * off[..., 1]
        - size[ev, 0, None] / 2
        - (size[None, :, 0] / 2 * c + size[None, :, 1] / 2 * s)
    )
    lat = (
        np.abs(ce * off[..., 1] - se * off[..., 0])
        - size[ev, 1, None] / 2
        - (size[None, :, 0] / 2 * s + size[None, :, 1] / 2 * c)
    )
    ok = (
        valid[None]
        & (gap > 0)
        & (yaw <= np.deg2rad(75))
        & (lat < 0)
        & ((lat < -0.5) | (yaw <= np.deg2rad(10)))
    )
    masked = np.where(ok, gap, np.inf)
    lead = masked.argmin(1)
    rel = speed[ev] - speed[lead]
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc = np.where(ok.any(1) & (rel > 0), np.minimum(masked.min(1) / rel, 5.0), 5.0)
    return nearest, ttc


def test_pruned_interactions_equal_the_all_pairs_reference():
    rng = np.random.default_rng(11)
    n, steps = 60, 30
    xy = rng.uniform(-40, 40, (1, n, steps, 2))
    heading = rng.choice([0.0, 0.05, -0.1, np.pi, 1.2], (1, n, steps)) + rng.normal(0, 0.02, (1, n, steps))
    size = np.column_stack([rng.uniform(0.5, 6.0, n), rng.uniform(0.5, 2.5, n)])
    speed = rng.uniform(0, 20, (1, n, steps))
    valid = rng.random((1, n, steps)) > 0.1
    ev = np.array([0, 3, 5, 17, 42])
    got = interaction_features(xy, heading, valid, size, speed, ev)
    for t in range(steps):
        nearest, ttc = _brute_force_interactions(
            xy[0, :, t], heading[0, :, t], valid[0, :, t], size, speed[0, :, t], ev
        )
        np.testing.assert_allclose(got.distance_to_nearest_object[0, :, t], nearest, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(got.time_to_collision[0, :, t], ttc, rtol=1e-4, atol=1e-4)
    assert (got.time_to_collision < 5).sum() > 5 and got.collision.sum() > 5
