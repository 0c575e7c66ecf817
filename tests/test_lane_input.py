"""The road input (ModelConfig.lane_input): road points and features in closed form, frame invariance, a
model extended with it starts as it was, the sampler reads exactly what training reads, and training on
its windows reaches its weights."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers import (
    REPO,
    assert_batched_ego_env_equals_separate_envs,
    bundle_scene,
    extended_tiny_checkpoint,
    greedy_window,
    random_scene_inputs,
    small_scenes,
    straight_road_scene,
    tiny_checkpoint,
)

from trajeglish_env.checkpoint import Checkpoint, load_into
from trajeglish_env.env import TrajeglishNPC
from trajeglish_env.geometry import to_local
from trajeglish_env.model import SceneInputs
from trajeglish_env.model.lanes import (
    EDGE_POINTS,
    LANE_POINTS,
    POSITION_SCALE,
    REACH,
    ROAD_POINTS,
    SOURCE_POINTS,
    SPACING,
    road_view,
    scene_road_points,
    window_road_view,
)
from trajeglish_env.model.neighbours import NeighbourView, batch_view, window_view
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.scenario import MapKind, Scenario
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.closed_loop import ClosedLoopConfig, closed_loop_batch, rolled_out_road
from trajeglish_env.training.dataset import collate_windows
from trajeglish_env.training.train import window_config
from trajeglish_env.training.training_data import TokenizedWindows


def _lane_checkpoint() -> Checkpoint:
    return extended_tiny_checkpoint("lane_input")


def _ring_scene() -> Scenario:
    """One vehicle on a counter-clockwise ring lane of radius 20 m, with the ring's two edges."""
    angle = np.linspace(0.0, 2 * math.pi, 253)
    ring = lambda r: np.stack([r * np.cos(angle), r * np.sin(angle)], -1)  # noqa: E731
    t = np.arange(20) * 0.1
    xyh = np.stack([20 * np.cos(t * 0.5), 20 * np.sin(t * 0.5), t * 0.5 + math.pi / 2], -1)[None]
    return Scenario.from_arrays(
        xyh,
        np.ones((1, 20), dtype=bool),
        np.array([[4.5, 2.0]]),
        np.array([0]),
        polylines=[ring(20.0), ring(18.0), ring(22.0)],
        polyline_kinds=[MapKind.LANE_SURFACE_STREET, MapKind.ROAD_EDGE_BOUNDARY, MapKind.ROAD_EDGE_BOUNDARY],
        scenario_id="ring",
        source="test",
    )


def test_road_points_follow_the_polylines_every_two_metres() -> None:
    sc = straight_road_scene(num_agents=2, steps=30)
    points = scene_road_points(sc)
    lanes, edges = points[points[:, 3] == 0], points[points[:, 3] == 1]
    assert len(lanes) == len(edges) == 2 * 226  # 449 m each: 0, 2, .., 448 m and the end; lines not read
    assert np.allclose(np.diff(lanes[:226, 0]), np.r_[np.full(224, SPACING), 1.0])
    assert np.allclose(points[:, 2], 0.0)  # every polyline runs along +x
    ring = scene_road_points(_ring_scene())
    lane = ring[ring[:, 3] == 0]
    tangent = np.arctan2(lane[:, 1], lane[:, 0]) + math.pi / 2  # counter-clockwise travel
    assert np.allclose(np.angle(np.exp(1j * (lane[:, 2] - tangent))), 0.0, atol=0.05)


def test_features_in_closed_form() -> None:
    """An agent on the lower lane of a straight two-lane road, facing +x: the lane points read are the
    nearest ones running its way (the ahead ones counted at half their distance), the edges the nearest edge
    points; points behind it by more than 5 m or farther than REACH are not read; a lane running the other
    way is not read."""
    sc = straight_road_scene(num_agents=2, steps=30)
    points = torch.from_numpy(scene_road_points(sc))
    xyh = torch.tensor([[100.0, 0.0, 0.0], [100.0, 0.0, math.pi]], dtype=torch.float64)
    feats, mask = road_view(
        points, torch.ones(len(points), dtype=torch.bool), xyh, torch.tensor([True, False])
    )
    assert feats.shape == (2, ROAD_POINTS, 6) and mask.shape == (2, ROAD_POINTS)
    assert not mask[1].any() and not feats[1].any()  # an agent not present reads nothing
    assert mask[0].all()
    lane, edge = feats[0, :LANE_POINTS] * POSITION_SCALE, feats[0, LANE_POINTS:] * POSITION_SCALE
    assert torch.equal(feats[0, :LANE_POINTS, 4], torch.ones(LANE_POINTS))
    assert torch.equal(feats[0, LANE_POINTS:, 5], torch.ones(EDGE_POINTS))
    # the lane points read: key = hypot(x / 2 if x > 0 else x, y); lane y = 0 (key |x| or x/2) and 3.5
    xs = np.arange(-50.0, 400.0, SPACING)
    lx = np.concatenate([xs - 100, xs - 100])
    ly = np.concatenate([np.zeros_like(xs), np.full_like(xs, 3.5)])
    keep = lx > -5
    key = np.hypot(np.where(lx > 0, lx / 2, lx), ly)[keep]
    want = np.sort(key)[:LANE_POINTS]
    lx_got, ly_got = lane[:, 0].numpy(), lane[:, 1].numpy()
    got = np.sort(np.hypot(np.where(lx_got > 0, lx_got / 2, lx_got), ly_got))
    assert np.allclose(got, want)
    assert float(lane[:, 0].max()) > 2 * float(-lane[:, 0].min())  # it reaches further ahead than back
    assert torch.allclose(feats[0, :, 2], torch.ones(ROAD_POINTS)) and not feats[0, :, 3].any()
    assert set(np.round(edge[:, 1].numpy(), 6)) <= {-1.75, 5.25}
    # facing the other way, the lanes run against it: only edges are read
    back = torch.tensor([[100.0, 0.0, math.pi]], dtype=torch.float64)
    feats, mask = road_view(points, torch.ones(len(points), dtype=torch.bool), back, torch.tensor([True]))
    assert not mask[0, :LANE_POINTS].any() and mask[0, LANE_POINTS:].all()
    # far from the road: nothing within REACH
    far = torch.tensor([[100.0, REACH + 6.0, 0.0]], dtype=torch.float64)
    _, mask = road_view(points, torch.ones(len(points), dtype=torch.bool), far, torch.tensor([True]))
    assert not mask.any()


def test_a_ring_reads_as_a_left_bend_ahead() -> None:
    sc = _ring_scene()
    points = torch.from_numpy(scene_road_points(sc))
    feats, mask = road_view(
        points,
        torch.ones(len(points), dtype=torch.bool),
        torch.from_numpy(sc.xyh[:, 0]),
        torch.tensor([True]),
    )
    lane = feats[0, :LANE_POINTS][mask[0, :LANE_POINTS]] * POSITION_SCALE
    ahead = lane[lane[:, 0] > 5]
    assert len(ahead) > 5 and (ahead[:, 1] > 0).all()  # the lane ahead lies to the left
    assert (feats[0, :LANE_POINTS][mask[0, :LANE_POINTS]][lane[:, 0] > 5, 3] > 0).all()  # and turns left


def test_features_do_not_depend_on_the_frame() -> None:
    sc = small_scenes()[0]
    points = scene_road_points(sc)
    frame = np.array([37.0, -12.0, 0.7])
    local = np.concatenate([to_local(frame, points[:, :3]), points[:, 3:]], -1)
    states, valid = sc.xyh[:, :12], sc.valid[:, :12]
    a = window_road_view(points, states, valid, 11)
    b = window_road_view(local, to_local(frame, states), valid, 11)
    assert a[1].any() and np.array_equal(a[1].sum(-1), b[1].sum(-1))
    # the same points (in either order: points that tie in distance may swap)
    np.testing.assert_allclose(np.sort(a[0], axis=-2), np.sort(b[0], axis=-2), atol=1e-5)


def test_an_extended_model_starts_as_the_checkpoint_did() -> None:
    base = tiny_checkpoint()
    cfg = dataclasses.replace(base.model.cfg, lane_input=True)
    model = TrajeglishModel(cfg)
    load_into(model, base, base.vocabulary)
    model.eval()
    a, t = cfg.max_agents, cfg.steps
    g = torch.Generator().manual_seed(0)
    scene = random_scene_inputs(cfg, g)
    tokens = torch.randint(0, cfg.vocab_size, (1, a, t), generator=g)
    states = torch.randn(1, a, t + 1, 3, generator=g) * 5
    view = window_view(states, torch.ones(1, a, t + 1, dtype=torch.bool), torch.ones(1, a, 2) * 4, t)
    road = torch.rand(1, t, a, ROAD_POINTS, 6, generator=g)
    view = NeighbourView(
        view.own, view.pairs, view.mask, road, torch.ones(1, t, a, ROAD_POINTS, dtype=torch.bool)
    )
    with torch.no_grad():
        torch.testing.assert_close(model(scene, tokens, view), base.model(scene, tokens), rtol=0, atol=0)
        with pytest.raises(ValueError, match="lane_input"):
            model(scene, tokens)
        with pytest.raises(ValueError, match="road features"):
            model(scene, tokens, dataclasses.replace(view, road=None, road_mask=None))


def test_sampling_reads_what_training_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Greedy decoding through prime + decode_at (the sampler's road features from its own states and the
    scene's road points, world frame) picks the argmax of the teacher-forced forward pass whose features
    come from the same states through the training windows' function (:func:`window_road_view`)."""
    ckpt = _lane_checkpoint()
    model = ckpt.model
    sc = straight_road_scene(num_agents=5, steps=30)
    gw = greedy_window(ckpt, monkeypatch, sc)
    t = model.cfg.steps
    view = window_view(*(torch.from_numpy(x)[None] for x in (gw.xyh, gw.valid, gw.size)), t)
    road, road_mask = window_road_view(scene_road_points(sc), gw.xyh, gw.valid, t)
    view = NeighbourView(
        view.own, view.pairs, view.mask, torch.from_numpy(road)[None], torch.from_numpy(road_mask)[None]
    )
    blind = dataclasses.replace(view, road_mask=torch.zeros_like(view.road_mask))
    with torch.no_grad():
        logits = model(gw.scene, gw.inputs, view)[0]
        plain = model(gw.scene, gw.inputs, blind)[0]
    assert gw.checked(logits) >= 3 * gw.horizon
    assert not torch.equal(logits, plain)  # the road changes the model's output


def test_training_windows_carry_the_road_and_train_its_weights() -> None:
    ckpt = _lane_checkpoint()
    model = ckpt.model.train()
    cfg = model.cfg
    ds = TokenizedWindows(small_scenes(), window_config(cfg), ckpt.vocabulary, None, seed=3)
    batch = collate_windows([ds[g] for g in range(2)])
    assert batch["road_points"].shape == (2, cfg.steps, cfg.max_agents, ROAD_POINTS, 6)
    real = batch["agent_mask"][:, None, :] & batch["agent_valid"][:, :, : cfg.steps].transpose(1, 2)
    assert batch["road_mask"].any(-1)[real].float().mean() > 0.9  # agents on the road read road points
    assert not batch["road_mask"][~real].any()
    view = batch_view(cfg.reads_states, batch)
    logits = model(SceneInputs.from_batch(batch), batch["input_tokens"], view)
    logits.logsumexp(-1).mean().backward()
    assert model.lanes.point[0].weight.grad is not None and model.lanes.point[0].weight.grad.abs().sum() > 0
    assert batch["road_source"].shape == (2, SOURCE_POINTS, 4) and batch["road_source_mask"].any(-1).all()


def test_closed_loop_windows_read_the_road_where_their_rollout_put_the_agents() -> None:
    """CAT-K with a road-reading model: the rollout reads the road around its own states (from the windows'
    ``road_source``), and the closed-loop windows carry those features, so teacher forcing them gives the
    logits the rollout chose from; the features of the logged states differ."""
    ckpt = _lane_checkpoint()
    model, cfg = ckpt.model, ckpt.model.cfg
    ds = TokenizedWindows(small_scenes(), window_config(cfg), ckpt.vocabulary, None, seed=3)
    batch = collate_windows([ds[g] for g in range(2)])
    k = 3
    closed = closed_loop_batch(model, batch, ckpt.vocabulary, ClosedLoopConfig(top_k=k, teacher_forced=False))
    assert not torch.equal(closed["road_points"], batch["road_points"])
    # and the states where they read it (the bend weights' flags compare the two)
    assert torch.equal(closed["agent_xyh"][:, :, 0], batch["agent_xyh"][:, :, 0])
    assert not torch.equal(closed["agent_xyh"], batch["agent_xyh"])
    # the logged states read from the road source give the windows' own features (the same points)
    logged = batch["agent_xyh"].double().numpy()
    logged = np.where(
        (batch["agent_valid"] & batch["agent_mask"][..., None]).numpy()[..., None], logged, np.nan
    )
    again, again_mask = rolled_out_road(batch, logged)
    assert torch.equal(again_mask, batch["road_mask"])
    torch.testing.assert_close(
        torch.sort(again, dim=-2).values, torch.sort(batch["road_points"], dim=-2).values, atol=1e-5, rtol=0
    )
    tokens = closed["input_tokens"]
    with torch.no_grad():
        logits = model(SceneInputs.from_batch(closed), tokens, batch_view(True, closed))
    chosen = tokens.transpose(1, 2)
    picked = logits.gather(-1, chosen.clamp(min=0)[..., None])
    assert int((logits > picked).sum(-1)[chosen >= 0].max()) < k


def test_batched_envs_with_road_reading_npcs_equal_separate_envs() -> None:
    """Each row keeps its own agents' road features (computed once per step and row): a batch of two scenes
    that end and restart plays as two separate envs do."""
    kw = {"npc": TrajeglishNPC(_lane_checkpoint()), "order": "last", "max_cycles": 5}
    assert_batched_ego_env_equals_separate_envs(kw)


def test_lane_distance_in_closed_form() -> None:
    sys.path.insert(0, str(REPO / "scripts"))
    from lone_vehicle_probe import lane_distance

    sc = straight_road_scene(num_agents=2, steps=30)  # lanes along +x at y = 0 and 3.5, x from -50 to 399
    xy = np.array([[10.0, 6.0], [10.0, -1.0], [10.0, 1.75], [-53.0, 4.0], [399.0, 0.0]])
    np.testing.assert_allclose(lane_distance(sc, xy), [2.5, 1.0, 1.75, math.hypot(3.0, 0.5), 0.0], atol=1e-9)


def test_scene_kinds_from_generated_ids() -> None:
    sys.path.insert(0, str(REPO / "scripts"))
    from lone_vehicle_probe import scene_kind

    sc = straight_road_scene(num_agents=2, steps=30)
    ids = ["highway-two-way-123", "sumo-grid-50050-1", "highway-racetrack-999000", "womd-abc", "x-12", "abc"]
    kinds = [scene_kind(dataclasses.replace(sc, scenario_id=i)) for i in ids]
    assert kinds == ["two-way", "grid", "racetrack", sc.source, sc.source, sc.source]


def test_lone_vehicle_probe_script(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The shipped model's sdc alone follows a straight highway in every rollout and leaves a roundabout in
    every one (docs/evaluation.md, "The road in the agent's own frame"; a model that reads the road changes
    the second count)."""
    save_scenarios(
        tmp_path / "s.scn.npz",
        [bundle_scene("highway-highway-999000"), bundle_scene("highway-roundabout-999000")],
    )
    script = [sys.executable, str(REPO / "scripts" / "lone_vehicle_probe.py"), "--rollouts", "4", "--json"]
    done = subprocess.run([*script, "--data", str(tmp_path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["by_kind"] == {
        "highway": {"off_road": 0, "rollouts": 4},
        "roundabout": {"off_road": 4, "rollouts": 4},
    }
    assert (result["scenes"], result["rollouts"], result["off_road"], result["rate"]) == (2, 8, 4, 0.5)
    bad = subprocess.run(
        [*script, "--data", str(tmp_path), "--distance", "0"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "--distance and --temperature > 0" in bad.stderr
