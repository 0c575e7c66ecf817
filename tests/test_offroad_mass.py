"""The off-road-mass training term (training/offroad_mass.py): the candidates it masks follow the reference
road-edge rule, logged positions whose own token leaves the road are left out, and a run trains with it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from helpers import grid_vocabulary, tiny_config

from trajeglish_env.checkpoint import load_checkpoint
from trajeglish_env.geometry import box_corners, to_global
from trajeglish_env.metrics.road_edges import RoadEdges, signed_distance_to_road_edges
from trajeglish_env.sampler.config import OFFROAD_MARGIN
from trajeglish_env.scenario import AgentKind, MapKind, Scenario
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.blocked_mass import term_loss
from trajeglish_env.training.dataset import ROLLOUT_SOURCE, WindowConfig, collate_windows, make_window
from trajeglish_env.training.offroad_mass import MARGIN, OffroadTerm, add_offroad_masks, offroad_candidates
from trajeglish_env.training.train import TrainConfig, train
from trajeglish_env.training.training_data import with_tokens

EDGES = (-1.75, 5.25)  # a two-lane road along +x: right edge drawn +x, left edge -x (road on the left)


def road_scene(steps: int = 40, seed: int = 0) -> Scenario:
    """Four vehicles and a cyclist on a straight two-lane road; the vehicles drift sideways now and then,
    one of them a little beyond the right edge for a while."""
    rng = np.random.default_rng(seed)
    n = 5
    t = np.arange(steps) * 0.1
    xyh = np.zeros((n, steps, 3))
    xyh[..., 0] = np.arange(n)[:, None] * 10.0 + rng.uniform(6, 14, n)[:, None] * t
    lane = np.array([0.0, 3.5, 0.0, 3.5, 0.0])[:, None]
    xyh[..., 1] = lane + 0.4 * np.sin(t * rng.uniform(1, 3, n)[:, None])
    xyh[4, 10:20, 1] = -1.3  # its right corners 0.55 m beyond the edge: off the road
    kind = np.full(n, AgentKind.VEHICLE)
    kind[1] = AgentKind.CYCLIST
    xs = np.arange(-50.0, 200.0, 1.0)
    right = np.stack([xs, np.full_like(xs, EDGES[0])], -1)
    left = np.stack([xs[::-1], np.full_like(xs, EDGES[1])], -1)
    return Scenario.from_arrays(
        xyh, np.ones((n, steps), bool), np.tile([4.5, 2.0], (n, 1)), kind, track_id=np.arange(n), sdc=0,
        polylines=[right, left], polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY] * 2,
        scenario_id=f"road-{seed}", source="test",
    )  # fmt: skip


def masked_window(scene: Scenario, positions: int = 1000, horizon: int = 1) -> dict[str, np.ndarray]:
    vocab = grid_vocabulary()
    window = make_window(scene, WindowConfig(steps=25, max_agents=8), np.random.default_rng(0))
    with_tokens([window], vocab)
    term = OffroadTerm(positions=positions, drawn=vocab.size, horizon=horizon)
    add_offroad_masks([window], [scene], vocab.templates, term, [np.random.default_rng(1)])
    return window


def test_the_masks_follow_the_reference_road_edge_rule() -> None:
    assert MARGIN == OFFROAD_MARGIN  # the guard's margin
    scene = road_scene()
    w = masked_window(scene)
    used = w["offroad_slot"] >= 0
    slot, step, mask = w["offroad_slot"][used], w["offroad_step"][used], w["offroad_mask"][used]
    # every vehicle target position is drawn (1000 >= all of them), no cyclist's
    vehicles = (w["agent_kind"] == AgentKind.VEHICLE) & w["agent_mask"]
    assert used.sum() == ((w["tokens"] >= 0) & vehicles[:, None]).sum()
    assert (w["agent_kind"][slot] == AgentKind.VEHICLE).all()
    # brute force: the reference signed distance of every candidate box's corners
    edges = RoadEdges.from_polylines([p for p in scene.polylines() if len(p) >= 2])
    origin = to_global(w["frame"], w["agent_xyh"][slot, step].astype(np.float64))
    size = w["agent_size"][slot].astype(np.float64)
    cand = to_global(origin[:, None], grid_vocabulary().templates[AgentKind.VEHICLE][None])
    excess = signed_distance_to_road_edges(box_corners(cand, size[:, None]), edges).max(-1)
    now = signed_distance_to_road_edges(box_corners(origin, size), edges).max(-1)
    want = excess > np.maximum(OFFROAD_MARGIN, now)[:, None]
    np.testing.assert_array_equal(mask, want)
    assert 0 < mask.any(1).sum() < len(mask)  # some positions have off-road candidates, some none
    assert (now > 0).any()  # ... the vehicle off the road among them, held to going no farther off


def test_a_horizon_masks_moves_that_kept_up_leave_the_road_within_it() -> None:
    """Horizon H: a candidate counts when the same move repeated H times (a constant turn) takes a corner
    beyond the edge at any of those steps; the reference rule step by step, and H = 1 is the one-step rule."""
    scene = road_scene()
    one, wide = masked_window(scene), masked_window(scene, horizon=10)
    np.testing.assert_array_equal(one["offroad_slot"], wide["offroad_slot"])  # the same positions drawn
    used = wide["offroad_slot"] >= 0
    slot, step = wide["offroad_slot"][used], wide["offroad_step"][used]
    edges = RoadEdges.from_polylines([p for p in scene.polylines() if len(p) >= 2])
    origin = to_global(wide["frame"], wide["agent_xyh"][slot, step].astype(np.float64))
    size = wide["agent_size"][slot].astype(np.float64)
    now = signed_distance_to_road_edges(box_corners(origin, size), edges).max(-1)
    moves = grid_vocabulary().templates[AgentKind.VEHICLE][None]
    state, want = origin[:, None], np.zeros(wide["offroad_mask"][used].shape, bool)
    for _ in range(10):
        state = to_global(state, moves)
        excess = signed_distance_to_road_edges(box_corners(state, size[:, None]), edges).max(-1)
        want |= excess > np.maximum(OFFROAD_MARGIN, now)[:, None]
    np.testing.assert_array_equal(wide["offroad_mask"][used], want)
    # every move off the road in one step is so kept up, and the horizon finds many more: the drifts that
    # reach the edge within a second
    assert (wide["offroad_mask"] >= one["offroad_mask"]).all()
    assert wide["offroad_mask"].sum() > 2 * one["offroad_mask"].sum()
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        OffroadTerm(horizon=0)


def test_logged_positions_whose_own_token_leaves_the_road_are_left_out() -> None:
    scene = road_scene()
    w = masked_window(scene)
    batch = collate_windows([w])
    drawn = batch["tokens"].clone()
    got = offroad_candidates(batch, drawn)
    used = np.flatnonzero(w["offroad_slot"] >= 0)
    mask = w["offroad_mask"][used]
    own = mask[np.arange(len(used)), w["tokens"][w["offroad_slot"][used], w["offroad_step"][used]]]
    assert own.any()  # the logged drift beyond the edge: its own tokens leave the road farther
    assert got.count == int((mask.any(1) & ~own).sum())
    # the versus-target form on them: log(1 + m / p) summed over the very same positions
    logits = torch.randn(1, batch["tokens"].shape[2], batch["tokens"].shape[1], got.mask.shape[1])
    p = torch.softmax(logits[got.batch, got.step, got.agent], -1)
    m = (p * torch.from_numpy(got.mask)).sum(-1)
    target = p.gather(1, drawn[got.batch, got.agent, got.step].long()[:, None])[:, 0]
    want = float(torch.log1p(m / target).sum())
    assert float(term_loss("versus_target", logits, got, drawn)) == pytest.approx(want, rel=1e-5)
    # make another position's own token one of its off-road candidates: it is no longer trained ...
    k = used[np.flatnonzero(mask.any(1) & ~own)[0]]
    a, t = int(w["offroad_slot"][k]), int(w["offroad_step"][k])
    drawn[0, a, t] = int(np.flatnonzero(w["offroad_mask"][k])[0])
    assert offroad_candidates(batch, drawn).count == got.count - 1
    # ... unless the tokens are a model's own rolled-out ones: then every position with such candidates is
    rolled = {**batch, "logged_targets": batch["logged_targets"] * 0}
    assert offroad_candidates(rolled, drawn).count == int(mask.any(1).sum())
    # a few positions per window, drawn at random
    assert (masked_window(scene, positions=4)["offroad_slot"] >= 0).sum() == 4
    with pytest.raises(ValueError, match="positions must be >= 1 per window, got 0"):
        OffroadTerm(positions=0)


@pytest.mark.parametrize("form", ["mass", "versus_target"])
def test_training_with_the_offroad_mass_term(tmp_path, form: str) -> None:
    scenes = [road_scene(seed=s) for s in range(4)]
    scenes[3] = replace(scenes[3], source="test" + ROLLOUT_SOURCE)
    save_scenarios(tmp_path / "data" / "a.scn.npz", scenes)
    cfg = TrainConfig(
        steps=3, batch_size=4, warmup_steps=1, val_every=100, log_every=1, checkpoint_every=3,
        num_workers=0, val_fraction=0.0, offroad_weight=2.0, offroad_positions=8, offroad_form=form,
        offroad_horizon=3,
    )  # fmt: skip
    vocab = grid_vocabulary()
    result = train(tmp_path / "data", tmp_path / "run", tiny_config(), cfg, vocabulary=vocab, progress=False)
    assert np.isfinite(result["train_loss"])
    saved = load_checkpoint(tmp_path / "run" / "last.pt").trainer["train_config"]
    assert (
        saved["offroad_weight"] == 2.0 and saved["offroad_positions"] == 8 and saved["offroad_form"] == form
    )
    assert saved["offroad_horizon"] == 3
    with pytest.raises(ValueError, match="offroad_horizon needs offroad_weight > 0"):
        TrainConfig(offroad_horizon=5)
    with pytest.raises(ValueError, match="offroad_horizon must be >= 1 step, got 0"):
        TrainConfig(offroad_weight=1.0, offroad_horizon=0)
    with pytest.raises(ValueError, match="offroad_form needs its term's weight > 0"):
        TrainConfig(offroad_form="versus_target")
    with pytest.raises(ValueError, match="offroad_weight >= 0 and offroad_positions >= 1"):
        TrainConfig(offroad_weight=-1.0)
    with pytest.raises(ValueError, match="masks are cut at logged states; closed_loop_top_k rolls"):
        TrainConfig(offroad_weight=1.0, closed_loop_top_k=3)


def test_the_train_command_sets_every_mass_term_field() -> None:
    from trajeglish_env.cli import build_parser
    from trajeglish_env.cli_mass_terms import mass_term_settings

    args = build_parser().parse_args(
        ["train", "--data", "d", "--out", "o", "--collision-weight", "60", "--collision-horizon", "10"]
        + ["--collision-sources", "sumo", "--collision-form", "versus-target", "--offroad-weight", "20"]
        + ["--offroad-positions", "8", "--offroad-horizon", "10", "--offroad-form", "versus-target"]
    )
    cfg = TrainConfig(**mass_term_settings(args))
    assert (cfg.collision_weight, cfg.collision_horizon, cfg.collision_sources) == (60.0, 10, ("sumo",))
    assert (cfg.offroad_weight, cfg.offroad_positions, cfg.offroad_horizon) == (20.0, 8, 10)
    assert cfg.collision_form == cfg.offroad_form == "versus_target" and not cfg.collision_rolled_out_only
    with pytest.raises(SystemExit):  # a horizon below one step is refused by the parser
        build_parser().parse_args(["train", "--data", "d", "--out", "o", "--offroad-horizon", "0"])
