"""Closed-loop rollouts: subset planning, sliding windows, partial control, external agents, determinism."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import grid_vocabulary, straight_road_scene, tiny_checkpoint, womd_tfrecord

from trajeglish_env.geometry import to_global
from trajeglish_env.sampler import RolloutEngine, SamplingConfig, plan_subsets, rollout
from trajeglish_env.scenario import AgentKind, Scenario


def crowd_scene(n: int = 210, steps: int = 40, seed: int = 0) -> Scenario:
    """``n`` agents on a 15 x 14 grid 8 m apart, all driving +x at 5-10 m/s."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(15) * 8.0, np.arange(14) * 8.0)
    start = np.stack([gx.ravel(), gy.ravel()], -1)[:n]
    speed = rng.uniform(5, 10, n)
    t = np.arange(steps) * 0.1
    xyh = np.zeros((n, steps, 3))
    xyh[..., 0] = start[:, :1] + speed[:, None] * t
    xyh[..., 1] = start[:, 1:]
    kind = np.where(np.arange(n) % 10 == 0, AgentKind.PEDESTRIAN, AgentKind.VEHICLE)
    size = np.where(kind[:, None] == AgentKind.PEDESTRIAN, [0.6, 0.6], [4.0, 1.8])
    return Scenario.from_arrays(
        xyh,
        np.ones((n, steps), bool),
        size,
        kind,
        sdc=17,
        scenario_id="crowd",
        polylines=[np.array([[0.0, y], [200.0, y]]) for y in np.arange(14) * 8.0],
        polyline_kinds=[1] * 14,
    )


@pytest.mark.parametrize("count", [0, -1, 1.5, True])
def test_rollout_names_a_bad_rollout_count(count: object) -> None:
    """``rollout(..., rollouts=0)`` said "rows must be >= 1, got 0", the engine's word for it."""
    with pytest.raises(ValueError, match=rf"rollout: rollouts must be an integer >= 1 .*got {count!r}"):
        rollout(tiny_checkpoint(), straight_road_scene(num_agents=2, steps=20), rollouts=count, horizon=2)


def test_subsets_cover_everyone_with_the_sdc_first_and_padding_first() -> None:
    sc = crowd_scene()
    pos = sc.xyh[:, 10, :2]
    active = np.ones(sc.num_agents, bool)
    active[5] = False
    plan = plan_subsets(pos, active, 24, first=sc.sdc)
    covered = np.unique(plan.slots[plan.slots >= 0])
    assert set(covered.tolist()) == set(np.flatnonzero(active).tolist())
    assert plan.centres[0] == sc.sdc and plan.acting_order[0] == sc.sdc
    assert plan.slots[0, -24] == sc.sdc  # a full subset: the sdc acts first in its slot order
    assert sorted(plan.acting_order.tolist()) == covered.tolist()
    rank = {a: i for i, a in enumerate(plan.acting_order)}
    for row in plan.slots:
        real = row[row >= 0]
        assert (row[: 24 - len(real)] == -1).all()  # padding first
        ranks = [rank[a] for a in real]
        assert ranks == sorted(ranks)  # agents that already acted come before the ones acting here
    # a scene smaller than the subset: one subset, padding in front
    small = plan_subsets(pos[:5], np.ones(5, bool), 24, first=2)
    assert small.num_subsets == 1 and (small.slots[0, :19] == -1).all() and small.slots[0, 19] == 2


def test_rollouts_are_deterministic_and_respect_control() -> None:
    sc = straight_road_scene(num_agents=5, steps=40)
    ckpt = tiny_checkpoint()
    controlled = np.array([True, True, False, True, False])
    a = rollout(ckpt, sc, rollouts=3, horizon=20, controlled=controlled, config=SamplingConfig(seed=1))
    b = rollout(ckpt, sc, rollouts=3, horizon=20, controlled=controlled, config=SamplingConfig(seed=1))
    c = rollout(ckpt, sc, rollouts=3, horizon=20, controlled=controlled, config=SamplingConfig(seed=2))
    assert a.xyh.shape == (3, 5, 31, 3)
    np.testing.assert_array_equal(a.xyh, b.xyh)
    assert not np.array_equal(a.xyh, c.xyh)
    cur = sc.current_index
    hist = np.where(sc.valid[:, : cur + 1, None], sc.xyh[:, : cur + 1], 0.0)
    np.testing.assert_array_equal(a.xyh[:, :, : cur + 1], np.broadcast_to(hist, (3, 5, cur + 1, 3)))
    log = np.where(sc.valid[~controlled, :31, None], sc.xyh[~controlled, :31], 0.0)
    np.testing.assert_array_equal(a.xyh[:, ~controlled], np.broadcast_to(log, (3, 2, 31, 3)))
    np.testing.assert_array_equal(
        a.valid[:, ~controlled], np.broadcast_to(sc.valid[~controlled, :31], (3, 2, 31))
    )
    assert a.valid[:, controlled, cur:].all()
    assert (
        (a.tokens[:, controlled, cur:30] >= 0) & (a.tokens[:, controlled, cur:30] < grid_vocabulary().size)
    ).all()
    # controlled motion is exactly the rendered tokens
    k = sc.kind[0]
    step = to_global(a.xyh[:, 0, cur + 3], grid_vocabulary().templates[k][a.tokens[:, 0, cur + 3]])
    np.testing.assert_allclose(step, a.xyh[:, 0, cur + 4], atol=1e-9)


def test_rollout_takes_a_checkpoint_file_or_the_shipped_name(tmp_path) -> None:
    from trajeglish_env.checkpoint import save_checkpoint

    sc, ckpt, cfg = straight_road_scene(num_agents=3, steps=30), tiny_checkpoint(), SamplingConfig(seed=1)
    path = save_checkpoint(tmp_path / "tiny.pt", ckpt.model, ckpt.vocabulary)
    from_file = rollout(str(path), sc, rollouts=2, horizon=4, config=cfg)
    np.testing.assert_array_equal(from_file.xyh, rollout(ckpt, sc, rollouts=2, horizon=4, config=cfg).xyh)
    assert rollout("shipped", sc, rollouts=1, horizon=2).xyh.shape == (1, 3, sc.current_index + 3, 3)
    with pytest.raises(TypeError, match="a Checkpoint, a checkpoint file or 'shipped'"):
        rollout(None, sc)  # type: ignore[arg-type]


def test_rollouts_split_over_processes_are_the_rollouts_of_one_process(monkeypatch) -> None:
    """Rollouts 0..4 in chunks 0-2 (here) and 3-4 (a forked worker) are those of one engine, bit for bit;
    the torch thread count is restored; a bad process count is refused."""
    import sys

    import torch

    from trajeglish_env.sampler import rollouts as module

    sc = straight_road_scene(num_agents=5, steps=40)
    ckpt = tiny_checkpoint()
    threads = torch.get_num_threads()
    one = rollout(ckpt, sc, rollouts=5, horizon=12, config=SamplingConfig(seed=3))
    splits = []
    real = module._split_rollouts
    monkeypatch.setattr(module, "_split_rollouts", lambda *a: splits.append(a[1:]) or real(*a))
    split = rollout(ckpt, sc, rollouts=5, horizon=12, config=SamplingConfig(seed=3), processes=2)
    assert splits == ([(5, 2)] if sys.platform.startswith("linux") else [])  # really forked on Linux
    for field in ("xyh", "valid", "tokens", "controlled"):
        np.testing.assert_array_equal(getattr(split, field), getattr(one, field))
    assert split.current_index == one.current_index and torch.get_num_threads() == threads
    assert len({a.tobytes() for a in one.tokens}) == 5  # five different rollouts
    auto = rollout(ckpt, sc, rollouts=5, horizon=12, config=SamplingConfig(seed=3), processes="auto")
    np.testing.assert_array_equal(auto.xyh, one.xyh)
    for bad in (0, -1, 1.5, "two", True):
        with pytest.raises(ValueError, match="processes must be a positive int or 'auto'"):
            rollout(ckpt, sc, rollouts=2, horizon=3, processes=bad)  # type: ignore[arg-type]


@pytest.mark.parametrize(("variant", "agents"), [("trajeglish", 210), ("no-intra", 60)])
def test_sliding_window_on_a_210_agent_scene_beyond_the_model_horizon(variant: str, agents: int) -> None:
    sc = crowd_scene(agents)
    ckpt = tiny_checkpoint(variant)  # 6 agents x 8 steps of context
    # prime 3: windows are recomputed at steps 10 and 15, so the rollout runs past one model window
    out = rollout(ckpt, sc, rollouts=2, horizon=7, config=SamplingConfig(prime_steps=3, seed=0))
    assert out.xyh.shape == (2, agents, 18, 3)
    assert out.valid[:, :, sc.current_index :].all()
    assert np.isfinite(out.xyh).all()
    moved = np.linalg.norm(out.xyh[:, :, -1, :2] - out.xyh[:, :, sc.current_index, :2], axis=-1)
    assert (moved < 7 * 3.6).all()  # at most 3.5 m per step with any template of this grid


def test_window_schedule_is_validated() -> None:
    sc = straight_road_scene(num_agents=3, steps=30)
    with pytest.raises(ValueError, match="recompute_every=9 must be in 1..6"):
        rollout(tiny_checkpoint(), sc, horizon=5, config=SamplingConfig(prime_steps=2, recompute_every=9))
    bad = sc.valid.copy()
    bad[1, 10] = False
    with pytest.raises(
        ValueError,
        match=r"controlled agents must be valid at the current step 10; track ids \[101, 102\] are not",
    ):
        rollout(tiny_checkpoint(), dataclasses.replace(sc, valid=bad), horizon=5, controlled=np.ones(3, bool))


def test_external_agent_is_asked_for_in_order_and_seen_by_later_agents() -> None:
    sc = straight_road_scene(num_agents=4, steps=30)
    ckpt = tiny_checkpoint()
    external = np.array([False, False, True, False])
    priority = np.array([1.0, 2.0, 0.0, 3.0])  # the external agent acts first
    controlled = ~external & sc.valid[:, sc.current_index]
    eng = RolloutEngine(ckpt, sc, 2, 5, controlled=controlled, external=external, priority=priority)
    asked = eng.advance()
    assert asked == 2 and eng.t == sc.current_index
    nxt = sc.xyh[2, sc.current_index] + np.array([1.0, 0.05, 0.01])
    eng.supply(2, nxt)
    assert eng.advance() is None and eng.t == sc.current_index + 1
    np.testing.assert_allclose(eng.xyh[:, 2, sc.current_index + 1], np.broadcast_to(nxt, (2, 3)))
    assert (eng.tokens[:, 2, sc.current_index] >= 0).all()
    with pytest.raises(RuntimeError, match=r"external agents \[2, 2\] of rows \[0, 1\] must be supplied"):
        eng.step()


def test_rollout_on_the_womd_sample() -> None:
    from trajeglish_env.sources.womd import read_womd

    sc = next(read_womd(womd_tfrecord()))
    out = rollout(tiny_checkpoint(), sc, rollouts=2, horizon=12, config=SamplingConfig(prime_steps=3))
    live = sc.valid[:, sc.current_index]
    assert live.sum() == 50
    assert out.valid[:, live, sc.current_index :].all()
    assert np.isfinite(out.xyh[out.valid]).all()


def test_cover_rule_needs_no_more_subsets_and_covers_everyone() -> None:
    sc = crowd_scene()
    pos = sc.xyh[:, 10, :2]
    active = np.ones(sc.num_agents, bool)
    paper = plan_subsets(pos, active, 24, first=sc.sdc)
    cover = plan_subsets(pos, active, 24, first=sc.sdc, rule="cover")
    assert set(np.unique(cover.slots[cover.slots >= 0]).tolist()) == set(range(sc.num_agents))
    assert cover.num_subsets < paper.num_subsets  # 210 agents: far fewer contexts than the paper's rule
    assert np.array_equal(cover.slots[0], paper.slots[0])  # the sdc's subset is the same
    assert len(np.unique(cover.acting_order)) == sc.num_agents
    with pytest.raises(ValueError, match="subset rule"):
        plan_subsets(pos, active, 24, first=sc.sdc, rule="nearest")
