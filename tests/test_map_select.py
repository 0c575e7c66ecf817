"""ModelConfig.map_select: a window holds the map chunks nearest its frame agent (the shipped model's
choice: with 0.5 m map points, 64 chunks reach only 26-49 m, so farther agents see no map) or those
nearest to any of its agents, so that every agent sees the road near it; ModelConfig.map_stride: a chunk
takes every Nth point of its polyline, so the same chunks show N times as much road."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import straight_road_scene, tiny_checkpoint

from trajeglish_env.checkpoint import Checkpoint, check_init, load_pretrained
from trajeglish_env.geometry import to_local
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.model.config import ModelConfig
from trajeglish_env.model.map_chunks import (
    AHEAD_STEPS,
    ahead_anchors,
    chunk_map,
    map_anchors,
    nearest_chunks,
    strided_points,
)
from trajeglish_env.sampler import SamplingConfig, rollout
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.training.dataset import WindowConfig, make_window
from trajeglish_env.training.train import window_config


def _map_gap(points: np.ndarray, point_mask: np.ndarray, agents_local: np.ndarray) -> np.ndarray:
    """``[A]`` distance from each agent (window frame) to the nearest map point the window holds."""
    pts = points[point_mask]
    return np.sqrt(((pts[None] - agents_local[:, None, :2]) ** 2).sum(-1)).min(-1)


def test_chunks_near_any_agent_reach_agents_far_from_the_frame() -> None:
    scene = straight_road_scene(num_agents=6, steps=40)  # 6 cars 12 m apart along a 1 m-spaced road
    chunks = chunk_map(scene, 20)  # 19 m chunks
    frame = scene.xyh[0, 0]
    agents = scene.xyh[scene.valid[:, 0], 0]
    local = to_local(frame, agents)
    pts, pmask, _, mask, _ = nearest_chunks(chunks, frame, 6, 100.0)
    assert mask.all() and _map_gap(pts, pmask, local).max() > 20.0  # the farthest car sees no road
    pts, pmask, _, mask, _ = nearest_chunks(chunks, frame, 6, 100.0, anchors=agents[:, :2])
    assert mask.all() and _map_gap(pts, pmask, local).max() < 1.0  # every car has a lane under it
    same = nearest_chunks(chunks, frame, 6, 100.0, anchors=frame[None, :2])
    frame_only = nearest_chunks(chunks, frame, 6, 100.0)
    assert all(np.array_equal(a, b) for a, b in zip(same, frame_only, strict=True))


@pytest.mark.parametrize("select", ["frame", "agents"])
def test_training_windows_follow_the_config(select: str) -> None:
    scene = straight_road_scene(num_agents=6, steps=40)
    cfg = WindowConfig(steps=9, max_agents=6, max_polylines=6, points_per_polyline=20, map_select=select)
    gaps = []
    for seed in range(6):
        w = make_window(scene, cfg, np.random.default_rng(seed))
        real = w["agent_mask"] & w["agent_valid"][:, 0]
        gaps.append(_map_gap(w["map_points"], w["map_point_mask"], w["agent_xyh"][real, 0]).max())
    if select == "agents":
        assert max(gaps) < 1.0
    else:
        assert max(gaps) > 10.0  # some window's frame agent is at one end of the queue


def test_training_windows_of_the_road_ahead_reach_farther_down_the_road() -> None:
    """The same windows (seeds) with 6 chunks: nearest the agents and where they drive to, the chunks reach
    farther along the frame agent's heading than nearest the agents alone."""
    scene = straight_road_scene(num_agents=6, steps=40)
    reach = {}
    for select in ("agents", "ahead"):
        cfg = WindowConfig(steps=9, max_agents=6, max_polylines=6, points_per_polyline=20, map_select=select)
        windows = [make_window(scene, cfg, np.random.default_rng(seed)) for seed in range(6)]
        reach[select] = np.array([w["map_points"][w["map_point_mask"]][:, 0].max() for w in windows])
    assert (reach["ahead"] >= reach["agents"]).all(), reach
    assert (reach["ahead"] > reach["agents"] + 5.0).sum() >= 5, reach  # in one window the same farthest chunk


def test_the_road_ahead_is_where_each_agent_would_be_at_its_speed_and_turn_rate() -> None:
    now = np.array([[10.0, 5.0, 0.0], [0.0, 0.0, 0.3], [3.0, 4.0, 1.0]])
    prev = np.array([[9.0, 5.0, 0.0], [-0.5 * np.cos(0.2), -0.5 * np.sin(0.2), 0.2], [0.0, 0.0, 0.0]])
    ok = np.array([True, True, False])
    got = ahead_anchors(now, prev, ok).reshape(1 + len(AHEAD_STEPS), 3, 2)
    np.testing.assert_allclose(got[0], now[:, :2])
    # straight at 1 m a step: 8, 16 and 24 m on
    np.testing.assert_allclose(got[1:, 0], [[18.0, 5.0], [26.0, 5.0], [34.0, 5.0]])
    # 0.5 m a step turning 0.1 rad a step: the vertices of a regular polygon, on one circle
    radius = 0.5 / (2 * np.sin(0.05))
    centre = now[1, :2] + radius * np.array([np.cos(0.3 - 0.05 + np.pi / 2), np.sin(0.3 - 0.05 + np.pi / 2)])
    np.testing.assert_allclose(np.hypot(*(got[1:, 1] - centre).T), radius, rtol=1e-9)
    np.testing.assert_allclose(got[1:, 2], np.broadcast_to(now[2, :2], (3, 2)))  # no step before: it stands
    assert map_anchors("frame", now, prev, ok) is None
    np.testing.assert_array_equal(map_anchors("agents", now, prev, ok), now[:, :2])
    np.testing.assert_array_equal(map_anchors("ahead", now, prev, ok), got.reshape(-1, 2))


def test_chunks_of_the_road_ahead_show_more_of_the_path_of_highway_env_vehicles() -> None:
    """The 16 bundled highway-env scenes, the shipped model's 64 chunks of 20 points: chosen nearest the
    agents and where they drive to, the chunks show 0.88 of the vehicles' next 2.4 s of path (a median
    2.4 s, all of it), against 0.49 (0.9 s) nearest the agents alone."""
    from trajeglish_env.env.scenes import load_bundle
    from trajeglish_env.map_coverage import CoverageConfig, coverage_by_kind

    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(16)]
    shipped = load_pretrained().config
    shown = {
        select: coverage_by_kind(
            scenes, dataclasses.replace(shipped, map_select=select), (1,), CoverageConfig(24)
        )
        for select in ("agents", "ahead")
    }
    agents, ahead = (shown[s]["all"]["stride 1"]["path_shown"] for s in ("agents", "ahead"))
    assert agents == pytest.approx(0.491, abs=0.002) and ahead == pytest.approx(0.881, abs=0.002)


def test_configs_checkpoints_and_fine_tuning() -> None:
    with pytest.raises(ValueError, match="map_select must be one of"):
        ModelConfig(map_select="lanes")
    shipped = load_pretrained()
    assert shipped.config.map_select == "agents"  # the shipped model (stop 29) sees the road near every agent
    check_init(shipped, dataclasses.replace(shipped.config, map_select="agents"), shipped.vocabulary)


def test_rollouts_of_an_agents_model_are_deterministic_and_see_far_lanes() -> None:
    base = tiny_checkpoint()
    cfg = dataclasses.replace(base.model.cfg, map_select="agents")
    model = TrajeglishModel(cfg).eval()
    model.load_state_dict(base.model.state_dict())
    ckpt = Checkpoint(model=model, vocabulary=base.vocabulary, training={})
    scene = straight_road_scene(num_agents=6, steps=40)
    # the one-step road rule (with the road ahead the untrained draws keep to the same few tokens)
    config = SamplingConfig(seed=3, guard_road_ahead=0.0, guard_step_change=0.0)
    a = rollout(ckpt, scene, 2, 6, config=config)
    b = rollout(ckpt, scene, 2, 6, config=config)
    np.testing.assert_array_equal(a.tokens, b.tokens)
    c = rollout(base, scene, 2, 6, config=config)
    assert not np.array_equal(a.tokens, c.tokens)  # the far cars' map context differs


def test_a_map_stride_keeps_every_nth_point_and_each_polylines_ends() -> None:
    offsets = np.array([0, 1, 5, 14])  # polylines of 1, 4 and 9 points
    index, new = strided_points(offsets, 4)
    assert index.tolist() == [0, 1, 4, 5, 9, 13] and new.tolist() == [0, 1, 3, 6]
    scene = straight_road_scene(num_agents=6, steps=40)  # 1 m map points
    plain, strided = chunk_map(scene, 20), chunk_map(scene, 20, 4)
    assert np.array_equal(chunk_map(scene, 20, 1).points, plain.points)
    step = np.hypot(*np.diff(strided.points[0][strided.mask[0]], axis=0).T)
    assert np.allclose(step, 4.0)  # 4 m between the points: a chunk of 20 shows 76 m of road, not 19
    assert strided.num_chunks < plain.num_chunks and set(strided.kind) == set(plain.kind)
    first = scene.map_points[scene.map_offsets[:-1]]
    last = scene.map_points[scene.map_offsets[1:] - 1]
    ends = [
        strided.points[strided.polyline == k][strided.mask[strided.polyline == k]] for k in range(len(first))
    ]
    assert all(
        np.array_equal(e[0], a) and np.array_equal(e[-1], b)
        for e, a, b in zip(ends, first, last, strict=True)
    )
    with pytest.raises(ValueError, match="stride must be >= 1"):
        chunk_map(scene, 20, 0)
    with pytest.raises(ValueError, match="map_stride must be an int >= 1, got 0"):
        ModelConfig(map_stride=0)


def test_a_strided_model_sees_farther_and_fine_tunes_from_one_that_did_not() -> None:
    base = tiny_checkpoint()
    cfg = dataclasses.replace(base.model.cfg, map_stride=4)
    check_init(base, cfg, base.vocabulary)  # inputs, not weights: the checkpoint's weights still fit
    assert load_pretrained().config.map_stride == 1  # written before the field: the shipped behaviour
    scene = straight_road_scene(num_agents=6, steps=40)
    reach = []
    for c in (base.model.cfg, cfg):
        w = make_window(scene, window_config(c), np.random.default_rng(0))
        reach.append(np.abs(w["map_points"][w["map_point_mask"]][:, 0]).max())
    assert reach[1] > 2.5 * reach[0]  # the same number of chunks reach much farther along the road
    model = TrajeglishModel(cfg).eval()
    model.load_state_dict(base.model.state_dict())
    ckpt = Checkpoint(model=model, vocabulary=base.vocabulary, training={})
    a = rollout(ckpt, scene, 2, 6, config=SamplingConfig(seed=3))
    b = rollout(ckpt, scene, 2, 6, config=SamplingConfig(seed=3))
    np.testing.assert_array_equal(a.tokens, b.tokens)
    engine = RolloutEngine(ckpt, scene, 1, 6, scene.valid[:, scene.current_index], config=SamplingConfig())
    spacing = np.hypot(*np.diff(engine.chunks[0].points[0][engine.chunks[0].mask[0]], axis=0).T)
    assert np.allclose(spacing, 4.0)  # the sampler's windows are cut as the training windows were
