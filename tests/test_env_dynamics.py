"""The pieces under the environment: kinematic bicycle and inverse actions, logged routes, the IDM and
constant-velocity NPCs, observations (vector and bev) and the scene sources."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import bundle_scene, small_scenes, straight_road_scene

from trajeglish_env.env import EnvConfig, IDMParams, ObservationConfig, VehicleLimits, raw_env
from trajeglish_env.env.actions import (
    DELTA_HIGH,
    action_towards,
    bicycle_step,
    class_limits,
    make_action_space,
)
from trajeglish_env.env.drivers import OrderedDriver
from trajeglish_env.env.npc import IDMNPC, ConstantVelocityNPC
from trajeglish_env.env.observations import BEV_CHANNELS, EGO_FEATURES, NEIGHBOUR_FEATURES, sample_map_points
from trajeglish_env.env.routes import logged_paths
from trajeglish_env.env.scenes import SceneFiles, scene_set
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.scenario import AgentKind, MapKind, Scenario
from trajeglish_env.scenario_io import save_scenarios

LIMITS = VehicleLimits()


def test_bicycle_model_limits_and_turning() -> None:
    start = np.array([0.0, 0.0, 0.0])
    nxt, v = bicycle_step(start, np.float64(10.0), np.array([1.0, 0.0]), np.float64(5.0), LIMITS, 0.1)
    assert v == pytest.approx(10.4)  # +4 m/s^2 for 0.1 s
    np.testing.assert_allclose(nxt, [1.02, 0.0, 0.0])  # mean speed 10.2 m/s
    _, v = bicycle_step(start, np.float64(0.3), np.array([-1.0, 0.0]), np.float64(5.0), LIMITS, 0.1)
    assert v == 0.0  # -6 m/s^2 stops, never reverses
    _, v = bicycle_step(start, np.float64(39.9), np.array([1.0, 0.0]), np.float64(5.0), LIMITS, 0.1)
    assert v == LIMITS.max_speed
    nxt, _ = bicycle_step(start, np.float64(10.0), np.array([0.0, 1.0]), np.float64(5.0), LIMITS, 0.1)
    steer = np.arctan(8.0 * 3.0 / 10.0**2)  # grip: 8 m/s^2 of lateral acceleration at 10 m/s, wheelbase 3 m
    assert LIMITS.steer_limit(10.0, 5.0) == pytest.approx(steer) and LIMITS.steer_limit(2.0, 5.0) == 0.5
    beta = np.arctan(np.tan(steer) / 2)
    assert nxt[2] == pytest.approx(10.0 / 1.5 * np.sin(beta) * 0.1)  # half wheelbase 0.6 * 5 / 2
    assert 10.0 * nxt[2] / 0.1 == pytest.approx(8.0, rel=0.05)  # lateral acceleration v * yaw rate
    assert nxt[1] > 0  # turning left (positive steering) moves left


def test_inverse_actions_reach_the_target() -> None:
    now, target = np.array([5.0, 2.0, 0.3]), np.array([6.1, 2.4, 0.33])
    delta = action_towards("delta", now, 11.0, target, 4.5, LIMITS, 0.1)
    assert make_action_space("delta", 1).contains(delta)
    cont = action_towards("continuous", now, 11.0, target, 4.5, LIMITS, 0.1)
    nxt, _ = bicycle_step(now, np.float64(11.0), cont.astype(np.float64), np.float64(4.5), LIMITS, 0.1)
    assert np.hypot(*(nxt[:2] - target[:2])) < 0.1 and abs(nxt[2] - target[2]) < 0.01
    far = action_towards("delta", now, 11.0, now + [30.0, 0.0, 0.0], 4.5, LIMITS, 0.1)
    assert far[0] == DELTA_HIGH[0]  # clipped to the space
    templates = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.2, 0.1, 0.05]])
    assert action_towards("token", now, 11.0, target, 4.5, LIMITS, 0.1, templates) == 2


def test_action_towards_refuses_a_target_that_is_no_state_naming_the_agent() -> None:
    """``action_towards(agent, [x, y])`` (no heading) was a bare ``IndexError: index 2 is out of bounds``."""
    env = raw_env(small_scenes()[:1], npc="replay")
    env.reset(seed=0)
    agent = env.agent_selection
    for target, shown in (([0, 0], r"\[0, 0\] \(shape \(2,\)\)"), ([0.0, np.nan, 0.0], r"\[0.0, nan, 0.0\]")):
        with pytest.raises(
            ValueError,
            match=rf"agent '{agent}': .* finite \(x, y, heading\) array of shape \(3,\), got {shown}",
        ):
            env.action_towards(agent, target)
    with pytest.raises(ValueError, match="got abc"):
        action_towards("delta", np.zeros(3), 1.0, "abc", 4.5, LIMITS, 0.1)


def test_logged_paths_resample_extend_and_project() -> None:
    t = np.arange(11)
    xyh = np.zeros((2, 11, 3))
    xyh[0, :, 0] = 2.0 * t  # 20 m straight along +x
    xyh[1, :, 1] = 3.0  # parked
    valid = np.ones((2, 11), dtype=bool)
    valid[0, 4] = False  # a gap is bridged
    paths = logged_paths(xyh, valid, spacing=1.0, extension=np.array([5.0, 0.0]))
    assert paths.length.tolist() == [25.0, 0.0] and paths.count.tolist() == [26, 1]
    p, h = paths.at(np.array([0, 0]), np.array([7.5, 24.0]))
    np.testing.assert_allclose(p, [[7.5, 0.0], [24.0, 0.0]])  # the extension continues straight
    s, lateral, _ = paths.project(np.array([0]), np.array([[12.3, 0.8]]), np.array([10.0]))
    assert s[0] == pytest.approx(12.3) and lateral[0] == pytest.approx(0.8)
    assert (paths.points[1] == [0.0, 3.0]).all()  # a one-point path, padded with that point


def two_car_scene(gap: float, leader_speed: float) -> Scenario:
    """An ego far behind, a follower at 10 m/s and a leader ``gap`` m ahead of it on a straight lane."""
    steps = 91
    t = np.arange(steps) * 0.1
    xyh = np.zeros((3, steps, 3))
    xyh[0, :, 0] = -200.0 + 10.0 * t  # ego, external
    xyh[1, :, 0] = 10.0 * t  # follower: its log drives through the leader
    xyh[2, :, 0] = 10.0 + gap + leader_speed * np.maximum(t - 1.0, 0.0)
    xs = np.arange(-300.0, 400.0, 1.0)
    lines = [np.stack([xs, np.full_like(xs, y)], -1) for y in (0.0, -1.75, 1.75)]
    return Scenario.from_arrays(
        xyh,
        np.ones((3, steps), dtype=bool),
        np.tile([4.5, 2.0], (3, 1)),
        np.full(3, AgentKind.VEHICLE),
        sdc=0,
        polylines=[lines[0], lines[1], lines[2][::-1]],
        polyline_kinds=[MapKind.LANE_FREEWAY, MapKind.ROAD_EDGE_BOUNDARY, MapKind.ROAD_EDGE_BOUNDARY],
        scenario_id="two-cars",
    )


def test_idm_follower_stops_behind_a_stopped_leader_and_speeds_up_on_a_free_road() -> None:
    scene = two_car_scene(gap=30.0, leader_speed=0.0)
    external = np.array([True, False, False])
    driver = OrderedDriver(IDMNPC(IDMParams()), scene, external, 80, np.array([-1.0, 0.0, 0.0]), seed=0)
    gaps, speeds = [], []
    for _ in range(80):
        assert driver.advance() == 0
        driver.supply(0, scene.xyh[0, driver.t + 1])
        assert driver.advance() is None
        t = driver.t
        gaps.append(driver.xyh[2, t, 0] - driver.xyh[1, t, 0] - 4.5)
        speeds.append(np.hypot(*(driver.xyh[1, t, :2] - driver.xyh[1, t - 1, :2])) / 0.1)
    # the leader's log ends stopped: the end of its path stops it; the follower stops behind it
    assert min(gaps) > 1.0 and speeds[-1] < 0.1 and gaps[-1] < 6.0
    assert np.abs(driver.xyh[1, 11:, 1]).max() == 0.0  # stays on its path
    free = two_car_scene(gap=300.0, leader_speed=10.0)
    driver = OrderedDriver(IDMNPC(IDMParams(min_desired_speed=20.0)), free, external, 30, np.zeros(3), seed=0)
    for _ in range(30):
        while (a := driver.advance()) is not None:
            driver.supply(a, free.xyh[a, driver.t + 1])
    speed = np.hypot(*(driver.xyh[1, -1, :2] - driver.xyh[1, -2, :2])) / 0.1
    assert 12.0 < speed < 20.0  # accelerating towards 20 m/s at under 1.5 m/s^2


def crossing_scene() -> Scenario:
    """An IDM car (agent 1) driving east along y = 0 at 8 m/s and a car (agent 0, external) crossing its
    path northwards along x = 30 at 8 m/s, in the log both at the crossing at about the same time."""
    steps = 91
    t = np.arange(steps) * 0.1
    xyh = np.zeros((2, steps, 3))
    xyh[0, :, 0], xyh[0, :, 1], xyh[0, :, 2] = 30.0, -30.0 + 8.0 * t, np.pi / 2
    xyh[1, :, 0] = 2.0 + 8.0 * t
    xs = np.arange(-50.0, 150.0, 1.0)
    return Scenario.from_arrays(
        xyh, np.ones((2, steps), dtype=bool), np.tile([4.5, 2.0], (2, 1)), np.full(2, AgentKind.VEHICLE),
        sdc=0, polylines=[np.stack([xs, np.zeros_like(xs)], -1), np.stack([np.full_like(xs, 30.0), xs], -1)],
        polyline_kinds=[MapKind.LANE_SURFACE_STREET] * 2, scenario_id="crossing",
    )  # fmt: skip


@pytest.mark.parametrize("yield_horizon", [3.0, 0.0])
def test_idm_yields_to_crossing_traffic(yield_horizon: float) -> None:
    scene = crossing_scene()
    external = np.array([True, False])
    driver = OrderedDriver(
        IDMNPC(IDMParams(yield_horizon=yield_horizon)), scene, external, 80, np.array([-1.0, 0.0]), seed=0
    )
    overlap = []
    for _ in range(80):
        assert driver.advance() == 0
        driver.supply(0, scene.xyh[0, driver.t + 1])
        assert driver.advance() is None
        t = driver.t
        overlap.append(box_collisions(driver.xyh[1, t], scene.size[1], driver.xyh[0, t], scene.size[0]))
    if yield_horizon:  # it brakes for the crossing car, lets it pass, then goes on
        assert not any(overlap) and driver.xyh[1, -1, 0] > 40.0  # through the crossing
    else:  # seen only once its box is on the path ahead: too late to stop
        assert any(overlap)


def test_idm_is_not_stopped_by_a_tailgater() -> None:
    scene = two_car_scene(gap=300.0, leader_speed=10.0)
    xyh = scene.xyh.copy()
    xyh[0, :, 0] = xyh[1, :, 0] - 4.5 - 0.3  # the external car 0.3 m behind the IDM car's rear bumper
    tailgated = Scenario.from_arrays(
        xyh, scene.valid, scene.size, scene.kind, sdc=0, polylines=scene.polylines(),
        polyline_kinds=scene.map_kind, scenario_id="tailgated",
    )  # fmt: skip
    driver = OrderedDriver(
        IDMNPC(IDMParams()), tailgated, np.array([True, False, False]), 20, np.zeros(3), seed=0
    )
    for _ in range(20):
        assert driver.advance() == 0
        driver.supply(0, tailgated.xyh[0, driver.t + 1])
        assert driver.advance() is None
    speed = np.hypot(*(driver.xyh[1, -1, :2] - driver.xyh[1, -2, :2])) / 0.1
    assert speed > 9.0  # it drives on at its speed (a follower within the margin is no leader)


def test_continuous_action_towards_covers_the_distance_ahead_and_ignores_lateral_offsets() -> None:
    start = np.zeros(3)
    for speed, ahead in ((10.0, 0.98), (10.0, 1.01), (2.0, 0.19)):  # braking, speeding up, slowing
        action = action_towards("continuous", start, speed, np.array([ahead, 0.0, 0.0]), 4.5, LIMITS, 0.1)
        nxt, _ = bicycle_step(start, np.float64(speed), action, np.float64(4.5), LIMITS, 0.1)
        assert nxt[0] == pytest.approx(ahead, abs=1e-5)
    # a target beside a stopped car is for the steering to reach, never a reason to speed up
    action = action_towards("continuous", start, 0.0, np.array([0.0, 0.5, 0.0]), 4.5, LIMITS, 0.1)
    assert action[0] <= 0.0


def test_constant_velocity_npcs_keep_their_last_step() -> None:
    scene = straight_road_scene(num_agents=3, steps=40)
    driver = OrderedDriver(
        ConstantVelocityNPC(), scene, np.array([True, False, False]), 5, np.zeros(3), seed=0
    )
    for _ in range(5):
        while (a := driver.advance()) is not None:
            driver.supply(a, scene.xyh[a, driver.t + 1])
    step = scene.xyh[1, 10] - scene.xyh[1, 9]
    np.testing.assert_allclose(driver.xyh[1, 15], scene.xyh[1, 10] + 5 * step)


def test_vector_observation_layout() -> None:
    e = raw_env(small_scenes(), npc="replay")
    e.reset(seed=0, options={"scene": 2})
    obs = e.observe(e.agent_selection)
    cfg = EnvConfig().obs
    assert obs.shape == e.observation_space(e.agent_selection).shape and obs.dtype == np.float32
    assert np.abs(obs).max() <= 1.0
    sc, i = e.scenario, e.agent_index(e.agent_selection)
    assert obs[0] == pytest.approx(sc.speed()[i, sc.current_index] / 30.0, rel=1e-5)
    assert obs[3] == pytest.approx(sc.size[i, 0] / 10.0) and obs[5] == 0.0  # no progress yet
    near = obs[EGO_FEATURES : EGO_FEATURES + NEIGHBOUR_FEATURES * cfg.neighbours].reshape(cfg.neighbours, -1)
    shown = near[near[:, 0] == 1]
    dist = np.hypot(shown[:, 1], shown[:, 2])
    assert len(shown) >= 1 and (np.diff(dist) >= 0).all()  # nearest first
    route = obs[-2 * cfg.route_points :].reshape(-1, 2)
    assert (route[:, 0] > 0).all() and np.abs(route[:, 1]).max() < 0.1  # the route lies ahead
    map_part = obs[EGO_FEATURES + NEIGHBOUR_FEATURES * cfg.neighbours : -2 * cfg.route_points].reshape(-1, 6)
    assert map_part[:, 0].all() and map_part[:, 5].any() and map_part[:, 3].any()  # edges and lanes seen


def test_bev_observation_draws_ego_route_map_and_agents() -> None:
    e = raw_env(small_scenes(), npc="replay", observation="bev", obs=ObservationConfig(bev_resolution=3.0))
    e.reset(seed=0, options={"scene": 2})
    bev = e.observe(e.agent_selection)
    n = EnvConfig().obs.bev_size
    assert bev.shape == (BEV_CHANNELS, n, n) and bev.dtype == np.uint8
    assert bev[4, n // 2, n // 2] == 255  # the ego sits at the centre
    assert (bev[4, : n // 2 - 4] == 128).any()  # its route is drawn ahead (upwards)
    assert bev[0].any() and (bev[1] == 255).any()  # lanes and road edges
    assert bev[2].any() and not bev[3].any()  # other agents, none moved yet (ego acts first)


def test_map_points_are_resampled_per_polyline() -> None:
    scene = straight_road_scene()
    points, category = sample_map_points(scene, 3.0)
    assert len(points) == 5 * 150  # 5 polylines of 450 m at 1 m spacing, kept every 3 m
    assert set(np.unique(category).tolist()) == {0, 1, 2}


def test_scene_sources(tmp_path: object) -> None:
    path = tmp_path / "shard.scn.npz"  # type: ignore[operator]
    save_scenarios(path, small_scenes())
    files = scene_set(tmp_path)
    assert isinstance(files, SceneFiles) and len(files) == 3
    assert files.get(files.index_of("highway-two-way-999000")).scenario_id == "highway-two-way-999000"
    assert len(scene_set(None)) == 20  # the shipped bundle
    generated = scene_set("highway:merge")
    assert generated.get(7).scenario_id == "highway-merge-7" and generated.index_of("highway-merge-7") == 7
    with pytest.raises(TypeError, match="scenes: expected None"):
        scene_set(42)


def test_a_directory_of_shards_keeps_its_scenes_loaded(tmp_path, monkeypatch) -> None:
    """Each draw from another shard loaded it again, making new scene objects (and new entries in the
    engines' per-scene caches: 277 -> 675 MB over 400 short episodes of 16 scenes in 2 shards): a drawn
    scene is now the same object while the loaded shards fit SHARD_CACHE_BYTES, the oldest dropped first."""
    import trajeglish_env.env.scenes as scenes_module

    scenes = small_scenes()
    for k, sc in enumerate(scenes):
        save_scenarios(tmp_path / f"shard-{k}.scn.npz", [sc])
    files = scene_set(tmp_path)
    first = files.get(0)
    assert files.get(2) is not first and files.get(1).scenario_id and files.get(0) is first
    monkeypatch.setattr(scenes_module, "SHARD_CACHE_BYTES", 1)  # room for the current shard only
    files = scene_set(tmp_path)
    first = files.get(0)
    assert files.get(0) is first and files.get(1) is not None and files.get(0) is not first


def test_bundle_scenes_are_held_out_and_small() -> None:
    from trajeglish_env.env.scenes import BUNDLE_SEED, bundle_path

    assert bundle_path().stat().st_size < 3_000_000
    bundle = scene_set(None)
    ids = [bundle.get(i).scenario_id for i in range(len(bundle))]
    seeds = [int(s.split("-")[-1]) for s in ids if s.startswith("highway-")]
    assert len(seeds) == 16 and min(seeds) >= BUNDLE_SEED
    assert sum(s.startswith("sumo-") for s in ids) == 4
    assert bundle_scene(ids[0]).num_agents >= 2


def test_continuous_actions_keep_each_class_within_the_speeds_its_tokens_follow() -> None:
    """A pedestrian or cyclist under full throttle tops out at its class's motion envelope (4 / 15 m/s),
    a vehicle at the vehicle limit (a pedestrian reached 17 m/s and the NPCs read it 0.6 m off)."""
    import trajeglish_env

    bundle = trajeglish_env.env().unwrapped.scenes
    scene = next(s for i in range(len(bundle)) if ((s := bundle.get(i)).kind == AgentKind.PEDESTRIAN).any())
    cur = scene.current_index
    walker = int(np.flatnonzero((scene.kind == AgentKind.PEDESTRIAN) & scene.valid[:, cur])[0])
    env = raw_env([scene], npc="replay", external=(int(scene.track_id[walker]),), max_cycles=60)
    env.reset(seed=0)
    agent = env.agent_selection
    for _ in range(60):
        if env.terminations[agent] or env.truncations[agent]:
            break
        env.step(np.array([1.0, 0.0], np.float32))
    assert env.unwrapped.sim.kin.speed[walker] == pytest.approx(4.0)
    walker_limits = class_limits(AgentKind.PEDESTRIAN, LIMITS)
    assert (walker_limits.max_speed, walker_limits.max_lateral_accel) == (4.0, 6.0)
    assert class_limits(AgentKind.VEHICLE, LIMITS) == LIMITS


def test_a_walker_or_cyclist_steering_hard_stays_where_its_tokens_follow() -> None:
    """Full throttle and full steering for 30 steps: the NPCs' tokenized view of an external pedestrian or
    cyclist stays within centimetres of it (with the vehicles' 8 m/s^2 of grip it drifted 3.6 m / 0.7 m)."""
    import warnings

    import trajeglish_env
    from trajeglish_env.env import RewardConfig

    bundle = trajeglish_env.env().unwrapped.scenes
    scene = bundle.get(bundle.index_of("sumo-random-999000-0-0"))
    keep_going = RewardConfig(
        terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
    )
    for track in (3, 56):  # a pedestrian, a cyclist
        env = trajeglish_env.parallel_env(scenes=[scene], external=(track,), reward=keep_going, max_cycles=30)
        env.reset(seed=0)
        (agent,) = env.agents
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no drift warning either
            for _ in range(30):
                env.step({agent: np.array([1.0, 1.0], np.float32)})
        raw = env.unwrapped
        engine, i, t = raw.batch.rows.engine, raw.agent_index(agent), raw.sim.t
        gap = np.linalg.norm(engine.mxyh[0, i, : t + 1, :2] - engine.xyh[0, i, : t + 1, :2], axis=-1)
        assert gap.max() < 0.2, (agent, gap.max())


def test_one_jerky_delta_step_costs_at_most_the_comfort_cap() -> None:
    """The comfort term reads a step's change of displacement as acceleration: a `delta` step from 1 m to
    5 m ahead read 400 m/s^2 and cost -0.66, more than half a collision; capped at 3 units (-0.015)."""
    from trajeglish_env.env.config import RewardConfig
    from trajeglish_env.env.rewards import step_reward

    config = RewardConfig()
    out = step_reward(
        config,
        np.zeros(3),
        np.full(3, 50.0),
        np.zeros(3, bool),
        np.zeros(3, bool),
        np.zeros(3, bool),
        np.array([400.0, 6.0, 0.0]),  # a jerk, full braking, nothing
        np.array([0.0, 8.0, 0.0]),
    )
    np.testing.assert_allclose(out.discomfort, [3.0, 1.0 + 5.0 / 3.0, 0.0])  # continuous actions: below it
    np.testing.assert_allclose(out.reward, [-0.015, -0.005 * 8.0 / 3.0, 0.0])
    with pytest.raises(ValueError, match="comfort_cap must be >= 0"):
        RewardConfig(comfort_cap=-1.0)
