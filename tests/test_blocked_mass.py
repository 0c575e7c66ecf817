"""The colliding-mass training term (training/blocked_mass.py): which candidates collide, the loss, the
rolled-out targets kept out of the likelihood, and a training run with it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from helpers import bundle_scene, grid_vocabulary, straight_road_scene, tiny_config

from trajeglish_env.checkpoint import load_checkpoint
from trajeglish_env.geometry import to_global
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.blocked_mass import (
    BlockedCandidates,
    batch_blocked,
    blocked_candidates,
    blocked_loss,
    logged_weights,
    versus_target_loss,
)
from trajeglish_env.training.dataset import ROLLOUT_SOURCE, WindowConfig, make_window
from trajeglish_env.training.term_sources import collision_scenes
from trajeglish_env.training.train import TrainConfig, train

CAR = (4.5, 2.0)


def forward_templates(count: int = 16) -> np.ndarray:
    """One class of ``count`` straight moves 0 .. 3 m (and a second class, a copy, unused)."""
    step = np.zeros((count, 3))
    step[:, 0] = np.linspace(0.0, 3.0, count)
    return np.stack([step, step])


def two_cars(gap: float, ahead_moves: float) -> tuple[np.ndarray, ...]:
    """One window: slot 0 padding, slot 1 a car ``gap`` m ahead (front to centre spacing) that moves
    ``ahead_moves`` m in step 0, slot 2 a car at the origin; 2 states, 1 target step."""
    xyh = np.zeros((1, 3, 2, 3))
    xyh[0, 1, 0] = (gap, 0.0, 0.0)
    xyh[0, 1, 1] = (gap + ahead_moves, 0.0, 0.0)
    xyh[0, 2, 1] = (1.0, 0.0, 0.0)
    valid = np.zeros((1, 3, 2), bool)
    valid[0, 1:] = True
    size = np.ones((1, 3, 2))
    size[0, 1:] = CAR
    kind = np.zeros((1, 3), np.int64)
    return xyh, valid, size, kind


def expected_mask(obstacle: np.ndarray, templates: np.ndarray) -> np.ndarray:
    """The candidates of the car at the origin whose box overlaps a car at ``obstacle [3]`` (brute force)."""
    cand = to_global(np.zeros(3), templates[0])
    return box_collisions(cand, np.array(CAR), np.broadcast_to(obstacle, cand.shape), np.array(CAR))


def test_colliding_candidates_against_the_obstacle_as_the_order_shows_it() -> None:
    templates = forward_templates()
    xyh, valid, size, kind = two_cars(gap=5.0, ahead_moves=1.0)
    tokens = np.full((1, 3, 1), -1)
    tokens[0, 1:, 0] = (0, 5)  # slot 2's logged token: 1 m forward, clear of the car ahead's next box
    got = blocked_candidates(xyh, valid, size, kind, tokens, templates)
    # slot 1 acts before slot 2: slot 2 sees it at its next state, 6 m ahead (moves over 1.5 m collide)
    assert got.count == 1 and (got.batch[0], got.agent[0], got.step[0]) == (0, 2, 0)
    want = expected_mask(xyh[0, 1, 1], templates)
    np.testing.assert_array_equal(got.mask[0], want)
    assert 0 < want.sum() < len(want)  # some moves reach it, some do not
    # the car ahead (slot 1) sees slot 2 at its current state (it acts later): nothing it can reach
    assert 1 not in got.agent.tolist()
    # the car ahead standing still is hit by more candidates
    still = two_cars(gap=5.0, ahead_moves=0.0)
    tokens[0, 2, 0] = 2  # 0.4 m: clear of it at 5 m
    tighter = blocked_candidates(*still, tokens, templates)
    assert tighter.mask[0].sum() > got.mask[0].sum()
    np.testing.assert_array_equal(tighter.mask[0], expected_mask(still[0][0, 1, 1], templates))


def test_overlapping_boxes_and_colliding_logs_are_left_out() -> None:
    templates = forward_templates()
    tokens = np.full((1, 3, 1), -1)
    tokens[0, 1:, 0] = (0, 5)
    # boxes overlapping already at the step: no move undoes that, so nothing is trained there
    xyh, valid, size, kind = two_cars(gap=3.0, ahead_moves=0.0)
    assert blocked_candidates(xyh, valid, size, kind, tokens, templates).count == 0
    # the logged token itself collides (2.4 m forward into a car 6 m ahead): the position is not trained
    xyh, valid, size, kind = two_cars(gap=6.0, ahead_moves=0.0)
    tokens[0, 2, 0] = 12
    assert expected_mask(xyh[0, 1, 1], templates)[12]
    assert blocked_candidates(xyh, valid, size, kind, tokens, templates).count == 0
    assert blocked_candidates(xyh, valid, size, kind, tokens, templates, logged=np.array([1])).count == 0
    # ... but a model's own rolled-out token that collides is no data: there the term matters most
    rolled = blocked_candidates(xyh, valid, size, kind, tokens, templates, logged=np.array([0]))
    assert rolled.count == 1 and rolled.mask[0, 12]
    with pytest.raises(ValueError, match="states of 2 steps need 1 target steps, got 2"):
        blocked_candidates(xyh, valid, size, kind, np.zeros((1, 3, 2), np.int64), templates)


def test_the_term_on_rolled_out_targets_alone_leaves_the_logged_ones_out() -> None:
    templates = forward_templates()
    xyh, valid, size, kind = two_cars(gap=5.0, ahead_moves=1.0)
    tokens = np.full((1, 3, 1), -1)
    tokens[0, 1:, 0] = (0, 5)  # a clear logged token beside colliding candidates: trained by default
    window = (xyh, valid, size, kind, tokens, templates)
    for logged, want in ((np.array([1]), 0), (np.array([0]), 1)):
        assert blocked_candidates(*window, logged=logged).count == 1
        only = blocked_candidates(*window, logged=logged, rolled_out_only=True)
        assert only.count == want  # the one target is logged (1) or the model's own (0)
    # the same candidates where the position counts
    np.testing.assert_array_equal(only.mask[0], expected_mask(xyh[0, 1, 1], templates))
    with pytest.raises(ValueError, match="rolled_out_only needs the windows' logged target counts"):
        blocked_candidates(*window, rolled_out_only=True)


def car_behind_a_standing_one() -> tuple[tuple, np.ndarray, BlockedCandidates]:
    """Two cars 6 m apart, the one ahead standing and the one behind drawing tokens 0 then 3: the scene
    (``blocked_candidates``' arguments but the tokens), the tokens and its blocked candidates."""
    templates = forward_templates()
    xyh, valid, size, kind = two_cars(gap=6.0, ahead_moves=0.0)
    tokens = np.full((1, 3, 1), -1)
    tokens[0, 1:, 0] = (0, 3)
    return (xyh, valid, size, kind), tokens, blocked_candidates(xyh, valid, size, kind, tokens, templates)


def test_blocked_loss_is_minus_log_of_the_free_mass_and_its_gradient_frees_it() -> None:
    _, tokens, got = car_behind_a_standing_one()
    logits = torch.randn(1, 1, 3, 16, dtype=torch.float64, requires_grad=True)  # [B,T,A,D]
    p = torch.softmax(logits[0, 0, 2], -1).detach().numpy()
    m = p[got.mask[0]].sum()
    loss = blocked_loss(logits, got)
    assert float(loss.detach()) == pytest.approx(-np.log(1 - m), rel=1e-6)  # computed in float32
    loss.backward()
    with torch.no_grad():
        after = torch.softmax((logits - 0.5 * logits.grad)[0, 0, 2], -1).numpy()
    assert after[got.mask[0]].sum() < m
    # nearly every candidate colliding: a constant, no gradient
    trapped = torch.zeros(1, 1, 3, 16, dtype=torch.float64, requires_grad=True)
    with torch.no_grad():
        trapped[0, 0, 2, got.mask[0]] = 20.0
    capped = blocked_loss(trapped, got)
    assert float(capped.detach()) == pytest.approx(-np.log(1 - 0.99), rel=1e-5)
    capped.backward()
    assert trapped.grad is not None and float(trapped.grad.abs().max()) == 0.0
    # no position: a zero that still backpropagates
    none = blocked_candidates(*two_cars(gap=30.0, ahead_moves=0.0), tokens, forward_templates())
    assert none.count == 0 and float(blocked_loss(logits, none).detach()) == 0.0


def test_the_versus_target_form_moves_the_colliding_mass_to_the_target_alone() -> None:
    scene, tokens, got = car_behind_a_standing_one()
    colliding = got.mask[0]
    assert colliding.any() and not colliding[3] and not colliding[0]  # standing (token 0) never collides
    targets = torch.from_numpy(tokens)
    logits = torch.randn(1, 1, 3, 16, dtype=torch.float64, requires_grad=True)
    p = torch.softmax(logits[0, 0, 2], -1).detach().numpy()
    loss = versus_target_loss(logits, got, targets)
    assert float(loss.detach()) == pytest.approx(np.log1p(p[colliding].sum() / p[3]), rel=1e-6)
    loss.backward()
    assert logits.grad is not None
    grad = logits.grad[0, 0, 2].numpy()
    moved = colliding.copy()
    moved[3] = True
    assert np.all(grad[~moved] == 0.0) and grad[3] < 0 and np.all(grad[colliding] > 0)
    # more mass on standing does not lower it (the mass form falls), so freezing is no way out
    stand = logits.detach().clone()
    stand[0, 0, 2, 0] += 5.0
    assert float(versus_target_loss(stand, got, targets)) == pytest.approx(float(loss.detach()), rel=1e-6)
    assert float(blocked_loss(stand, got)) < float(blocked_loss(logits.detach(), got))
    # a model's own rolled-out target that collides is no anchor: the position is left out
    rolled = tokens.copy()
    rolled[0, 2, 0] = int(np.flatnonzero(colliding)[0])
    own = blocked_candidates(*scene, rolled, forward_templates(), logged=np.array([0]))
    assert own.count == 1
    assert float(versus_target_loss(logits, own, torch.from_numpy(rolled)).detach()) == 0.0


def test_rolled_out_targets_are_kept_out_of_the_likelihood() -> None:
    scene = bundle_scene("highway-merge-999000")
    config = WindowConfig(steps=25, max_agents=8)
    logged = make_window(scene, config, np.random.default_rng(0))
    assert logged["logged_targets"] == 24
    rolled = replace(scene, source=scene.source + ROLLOUT_SOURCE)
    window = make_window(rolled, config, np.random.default_rng(0))
    start = int(window["start"])
    assert window["logged_targets"] == min(max(scene.current_index - start, 0), 24)
    batch = {
        "tokens": torch.zeros(2, 3, 24, dtype=torch.long),
        "logged_targets": torch.tensor([24, 5]),
    }
    w = logged_weights(batch, None)
    assert w is not None and w.shape == (2, 3, 24)
    assert w[0].sum() == 72 and w[1, 0, :5].tolist() == [1.0] * 5 and w[1, 0, 5:].sum() == 0
    assert logged_weights({**batch, "logged_targets": torch.tensor([24, 24])}, None) is None
    doubled = logged_weights(batch, torch.full((2, 3, 24), 2.0))
    assert doubled is not None and doubled[1, 2, 4] == 2.0 and doubled[1, 2, 5] == 0.0


@pytest.mark.parametrize(
    ("rolled_out_only", "sources"),
    [(False, ()), (True, ()), (False, ("test",))],
    ids=["all-targets", "rolled-out-only", "one-source"],
)
def test_training_with_the_colliding_mass_term(
    tmp_path, rolled_out_only: bool, sources: tuple[str, ...]
) -> None:
    form = "versus_target" if sources else "mass"
    scenes = [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(4)]
    # half of them a model's rollouts: their windows train past the current step by the term alone
    scenes[2:] = [replace(s, source=s.source + ROLLOUT_SOURCE) for s in scenes[2:]]
    save_scenarios(tmp_path / "data" / "a.scn.npz", scenes)
    cfg = TrainConfig(
        steps=4, batch_size=4, warmup_steps=1, val_every=100, log_every=1, checkpoint_every=4,
        num_workers=0, val_fraction=0.0, collision_weight=2.0, collision_horizon=5,
        collision_rolled_out_only=rolled_out_only, collision_sources=sources, collision_form=form,
    )  # fmt: skip
    vocab = grid_vocabulary()
    result = train(tmp_path / "data", tmp_path / "run", tiny_config(), cfg, vocabulary=vocab, progress=False)
    assert np.isfinite(result["train_loss"])
    saved = load_checkpoint(tmp_path / "run" / "last.pt").trainer["train_config"]
    assert saved["collision_weight"] == 2.0 and saved["collision_horizon"] == 5
    assert saved["collision_rolled_out_only"] is rolled_out_only
    assert tuple(saved["collision_sources"]) == sources and saved["collision_form"] == form
    with pytest.raises(ValueError, match="collision_form must be one of"):
        TrainConfig(collision_weight=1.0, collision_form="hinge")
    with pytest.raises(ValueError, match="collision_form needs its term's weight > 0"):
        TrainConfig(collision_form="versus_target")
    with pytest.raises(ValueError, match="collision_weight must be >= 0, got -1"):
        TrainConfig(collision_weight=-1.0)
    with pytest.raises(ValueError, match="collision_horizon must be >= 1 step, got 0"):
        TrainConfig(collision_horizon=0)
    # a horizon or the rolled-out-only flag without the term did nothing, silently
    with pytest.raises(ValueError, match="collision_horizon needs collision_weight > 0"):
        TrainConfig(collision_horizon=3)
    with pytest.raises(ValueError, match="collision_rolled_out_only needs collision_weight > 0"):
        TrainConfig(collision_rolled_out_only=True)


def follow_window(gap: float, ahead_speed: float, steps: int) -> tuple[np.ndarray, ...]:
    """One window of ``steps + 1`` states: slot 1 a car ``gap`` m ahead moving ``ahead_speed`` m a step,
    slot 2 a car at the origin (its later states far aside: only its step-0 target is set)."""
    xyh = np.zeros((1, 3, steps + 1, 3))
    xyh[0, 1, :, 0] = gap + ahead_speed * np.arange(steps + 1)
    xyh[0, 2, 1:, 1] = 50.0
    valid = np.zeros((1, 3, steps + 1), bool)
    valid[0, 1:] = True
    size = np.ones((1, 3, 2))
    size[0, 1:] = CAR
    return xyh, valid, size, np.zeros((1, 3), np.int64)


def kept_up_mask(xyh: np.ndarray, horizon: int, templates: np.ndarray) -> np.ndarray:
    """Brute force: slot 2's candidates whose move, repeated h = 1 .. horizon times, overlaps slot 1 at its
    window state of step h (slot 1 acts first, so at h = 1 the guard's rule is the same state)."""
    hit = np.zeros(templates.shape[1], bool)
    for v in range(templates.shape[1]):
        state = np.zeros(3)
        for h in range(1, horizon + 1):
            state = to_global(state, templates[0, v])
            hit[v] |= bool(box_collisions(state, np.array(CAR), xyh[0, 1, h], np.array(CAR)))
    return hit


def test_a_horizon_counts_the_moves_that_stay_on_a_collision_course() -> None:
    templates = forward_templates()
    steps = 6
    tokens = np.full((1, 3, steps), -1)
    tokens[0, 2, 0] = 1  # 0.2 m a step: clear of the car ahead for the whole horizon
    xyh, valid, size, kind = follow_window(gap=12.0, ahead_speed=0.0, steps=steps)
    # one step: no move of at most 3 m reaches a car 12 m ahead
    assert blocked_candidates(xyh, valid, size, kind, tokens, templates).count == 0
    for horizon in (3, 5):
        got = blocked_candidates(xyh, valid, size, kind, tokens, templates, horizon=horizon)
        want = kept_up_mask(xyh, horizon, templates)
        assert got.count == 1 and (got.agent[0], got.step[0]) == (2, 0)
        np.testing.assert_array_equal(got.mask[0], want)
    # kept up 5 steps, moves over 1.5 m a step reach the standing car's tail (7.5 m away)
    assert kept_up_mask(xyh, 5, templates).sum() > kept_up_mask(xyh, 3, templates).sum() > 0
    assert not kept_up_mask(xyh, 5, templates)[:8].any() and kept_up_mask(xyh, 5, templates)[8:].all()
    # the car ahead driving off at 1 m a step: only faster moves close in; the window's states are used
    away = follow_window(gap=12.0, ahead_speed=1.0, steps=steps)
    moving = blocked_candidates(*away, tokens, templates, horizon=5)
    np.testing.assert_array_equal(moving.mask[0], kept_up_mask(away[0], 5, templates))
    assert 0 < moving.mask[0].sum() < kept_up_mask(xyh, 5, templates).sum()
    # the horizon ends with the window: from its last target step only one step is looked at
    last = np.full((1, 3, steps), -1)
    last[0, 2, steps - 1] = 1
    assert blocked_candidates(xyh, valid, size, kind, last, templates, horizon=5).count == 0
    # a logged token on a collision course is data: its position is left out
    tokens[0, 2, 0] = 15
    assert blocked_candidates(xyh, valid, size, kind, tokens, templates, horizon=5).count == 0
    with pytest.raises(ValueError, match="horizon must be >= 1 step, got 0"):
        blocked_candidates(xyh, valid, size, kind, tokens, templates, horizon=0)


class _Drawn:
    """A stand-in model whose drawn targets are the tokens themselves (the templates' own indices)."""

    @staticmethod
    def drawn_targets(tokens: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
        return tokens


def test_the_term_on_some_sources_reads_their_windows_alone() -> None:
    templates = forward_templates()
    steps = 6
    tokens = np.full((1, 3, steps), -1)
    tokens[0, 2, :2] = 1
    windows = [
        follow_window(12.0, 0.0, steps),
        follow_window(12.0, 0.0, steps),
        follow_window(12.0, 1.0, steps),
    ]
    xyh, valid, size, kind = (np.concatenate(parts) for parts in zip(*windows, strict=True))
    batch = {
        "agent_xyh": torch.from_numpy(xyh),
        "agent_valid": torch.from_numpy(valid),
        "agent_mask": torch.from_numpy(valid.any(-1)),
        "agent_size": torch.from_numpy(size),
        "agent_kind": torch.from_numpy(kind),
        "tokens": torch.from_numpy(np.repeat(tokens, 3, axis=0)),
        "logged_targets": torch.full((3,), steps),
        "scene": torch.tensor([2, 0, 1]),  # the windows' scenes: highway-env, SUMO, a SUMO rollout
    }
    everywhere = batch_blocked(_Drawn(), batch, templates, horizon=5)
    assert sorted(set(everywhere.batch.tolist())) == [0, 1, 2]
    term = collision_scenes(["sumo", "sumo+rollout", "highway"], ["sumo"])
    assert term is not None and term.tolist() == [True, True, False]
    rows = np.flatnonzero(term[batch["scene"]])
    assert rows.tolist() == [1, 2]
    some = batch_blocked(_Drawn(), batch, templates, horizon=5, rows=rows)
    keep = everywhere.batch > 0  # the positions of windows 1 and 2, as found in the whole batch
    for name in ("batch", "agent", "step", "mask"):
        np.testing.assert_array_equal(getattr(some, name), getattr(everywhere, name)[keep])
    none = batch_blocked(_Drawn(), batch, templates, horizon=5, rows=np.zeros(0, np.int64))
    assert none.count == 0 and none.mask.shape == (0, templates.shape[1])
    assert collision_scenes(["sumo", "highway"], []) is None
    with pytest.raises(
        ValueError,
        match="--collision-sources womd: no training scene has that source; the sources there: highway, sumo",
    ):
        collision_scenes(["sumo+rollout", "highway"], ["sumo", "womd"])
    with pytest.raises(ValueError, match="collision_sources needs collision_weight > 0"):
        TrainConfig(collision_sources=("sumo",))
