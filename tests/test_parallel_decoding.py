"""Parallel (fixed-point) decoding of the agents of a step draws the tokens sequential decoding draws, in
far fewer model calls (trajeglish_env.sampler.parallel)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import straight_road_scene, tiny_checkpoint, womd_tfrecord

from trajeglish_env.metrics.collision_fault import collisions_by_fault
from trajeglish_env.sampler import RolloutEngine, SamplingConfig
from trajeglish_env.sampler.engine import BatchEngine
from trajeglish_env.sampler.parallel import accepted, guard_view, kept_every_draft
from trajeglish_env.sampler.rows import RowSpec


def _run(
    sc, mode: str, guard: bool, rollouts: int = 2, horizon: int = 8, external=None, ahead: float | None = None
):  # type: ignore[no-untyped-def]
    """Tokens and model calls of a rollout whose external agent (if any) replays its log (``ahead``: the
    guard's road-ahead distance, default the env's)."""
    live = sc.valid[:, sc.current_index]
    ext = np.zeros(sc.num_agents, bool) if external is None else external
    road = {} if ahead is None else {"guard_road_ahead": ahead}
    # the untrained model's draws: the speed-change rule would mask them down to a few tokens (its own test)
    cfg = SamplingConfig(seed=5, guard=guard, intra_step=mode, guard_step_change=0.0, **road)
    eng = RolloutEngine(tiny_checkpoint(), sc, rollouts, horizon, live & ~ext, external=ext, config=cfg)
    while eng.stepping.any():
        agent = eng.advance()
        if agent is not None:
            eng.supply(agent, np.broadcast_to(sc.xyh[agent, eng.t + 1], (rollouts, 3)))
    return eng.tokens.copy(), eng.xyh.copy(), eng.model_calls


@pytest.mark.parametrize(("guard", "ahead"), [(False, 0.0), (True, 0.0), (True, None)])
def test_parallel_decoding_draws_the_sequential_tokens_in_fewer_calls(
    guard: bool, ahead: float | None
) -> None:
    sc = straight_road_scene(num_agents=6, steps=40)
    seq_tokens, seq_xyh, seq_calls = _run(sc, "sequential", guard, ahead=ahead)
    par_tokens, par_xyh, par_calls = _run(sc, "parallel", guard, ahead=ahead)
    np.testing.assert_array_equal(par_tokens, seq_tokens)
    np.testing.assert_array_equal(par_xyh, seq_xyh)
    # 5 sampled agents a step (the last enters late): 5 calls a step sequentially, fewer in parallel (the
    # untrained tiny model's draws barely repeat, and with the guard its random draws, vehicles and the
    # cyclist 0.75 m from the kerb, are mostly masked away from the drafts, so a draft rarely survives;
    # the shipped model needs about 2 a step, below)
    # (with the road ahead the untrained draws are masked to the few candidates that keep to the road
    # farthest, so no draft survives: 40 calls, never more than sequentially; 39 with the one-step rule)
    assert seq_calls == 8 * 5
    if not guard:
        assert par_calls <= 0.7 * seq_calls
    else:
        assert par_calls < seq_calls if ahead == 0 else par_calls <= seq_calls


def test_parallel_decoding_waits_for_an_external_agent_in_the_middle() -> None:
    sc = straight_road_scene(num_agents=6, steps=40)
    external = np.zeros(6, bool)
    external[2] = True  # acts third (slot order follows the sdc-first plan)
    seq = _run(sc, "sequential", True, external=external)
    par = _run(sc, "parallel", True, external=external)
    np.testing.assert_array_equal(par[0], seq[0])
    end = sc.current_index + 9
    np.testing.assert_array_equal(par[1][:, 2, :end], np.broadcast_to(sc.xyh[2, :end], (2, end, 3)))


def test_parallel_decoding_equals_sequential_with_a_logged_agent_closing_in() -> None:
    """Two sampled cars and a logged one closing in on the first from behind: the guard of the first sees
    the logged move only when it acts after it (RowStates.guard_moved), the same in both modes."""
    import dataclasses

    sc = straight_road_scene(num_agents=3, steps=40)
    t = np.arange(sc.num_steps) * 0.1
    xyh = np.zeros_like(sc.xyh)
    xyh[0, :, 0], xyh[1, :, 0], xyh[2, :, 0] = 9.6 + 5.0 * t, 10.0 * t, 30.0 + 5.0 * t
    xyh[2, :, 1] = 3.5
    sc = dataclasses.replace(sc, xyh=xyh, valid=np.ones_like(sc.valid), kind=np.zeros(3, np.int64))
    controlled = np.array([True, False, True])
    struck = {}
    for place, first in (("first", -1.0), ("last", 1.0)):
        tokens = {}
        for mode in ("sequential", "parallel"):
            # the one-step road rule: the road ahead keeps the untrained sdc out of the logged car's way
            cfg = SamplingConfig(
                temperature=1.0,
                seed=2,
                guard=True,
                intra_step=mode,
                guard_road_ahead=0.0,
                guard_step_change=0.0,  # the untrained car ahead slows at random (the collision to test)
            )
            priority = np.array([first, 0.0, -2.0])  # agent 2 acts first: the parallel call drafts it
            eng = RolloutEngine(tiny_checkpoint(), sc, 16, 15, controlled, config=cfg, priority=priority)
            eng.run()
            tokens[mode] = eng.tokens.copy()
            hit, _ = collisions_by_fault(eng.xyh, eng.valid, sc.size, 0, sc.current_index)
            struck[place, mode] = int(hit.sum())
        np.testing.assert_array_equal(tokens["parallel"], tokens["sequential"])
    assert struck["first", "parallel"] >= 10 and struck["last", "parallel"] <= 2, struck


def test_parallel_decoding_of_a_real_womd_scene_in_a_batch() -> None:
    """50 agents (several contexts of the tiny model) in rows of a batch: parallel = sequential, per row."""
    from trajeglish_env.sources.womd import read_womd

    sc = next(read_womd(womd_tfrecord()))
    live = sc.valid[:, sc.current_index]
    out = {}
    for mode in ("sequential", "parallel"):
        eng = BatchEngine(tiny_checkpoint(), 3, SamplingConfig(intra_step=mode, prime_steps=3))
        eng.start_rows([0, 1, 2], RowSpec(sc, 6, live), [11, 12, 13])
        eng.run()
        out[mode] = (eng.tokens.copy(), eng.model_calls)
    np.testing.assert_array_equal(out["parallel"][0], out["sequential"][0])
    assert out["parallel"][1] < out["sequential"][1]


def test_the_shipped_model_decodes_a_24_agent_step_in_about_two_calls() -> None:
    from trajeglish_env.benchmark.measure import benchmark_scenes
    from trajeglish_env.checkpoint import load_pretrained

    sc = benchmark_scenes(24)[0]
    live = sc.valid[:, sc.current_index]
    assert live.sum() == 24
    out = {}
    for mode in ("sequential", "parallel"):
        # float32: each row's result is independent of the batch on every CPU; bfloat16 GEMMs are not on
        # all of them (README "Speed", compute_dtype)
        config = SamplingConfig(intra_step=mode, compute_dtype="float32")
        eng = RolloutEngine(load_pretrained(), sc, 1, 6, live, config=config)
        eng.run()
        out[mode] = (eng.tokens.copy(), eng.model_calls)
    np.testing.assert_array_equal(out["parallel"][0], out["sequential"][0])
    assert out["sequential"][1] == 6 * 24
    assert out["parallel"][1] <= 6 * 3


def test_with_the_ego_acting_last_a_step_takes_about_one_call() -> None:
    """The shipped model's 23 NPCs before an external sdc acting last: a call whose every draw keeps its
    draft decides its whole chunk, the sdc's position after the last NPC included, so the step needs no
    second call for it once the sdc's state is supplied (26 calls for these 12 steps before)."""
    from trajeglish_env.benchmark.measure import benchmark_scenes
    from trajeglish_env.checkpoint import load_pretrained

    sc = benchmark_scenes(24)[0]
    external = np.zeros(sc.num_agents, bool)
    external[sc.sdc] = True
    priority = np.where(external, 1.0, 0.0)
    out = {}
    for mode in ("sequential", "parallel"):
        config = SamplingConfig(intra_step=mode, compute_dtype="float32")
        live = sc.valid[:, sc.current_index] & ~external
        eng = RolloutEngine(
            load_pretrained(), sc, 1, 12, live, external=external, config=config, priority=priority
        )
        while eng.stepping.any():
            agent = eng.advance()
            if agent is not None:
                eng.supply(agent, sc.xyh[agent, eng.t + 1][None])
        out[mode] = (eng.tokens.copy(), eng.model_calls)
    np.testing.assert_array_equal(out["parallel"][0], out["sequential"][0])
    assert out["sequential"][1] == 12 * 24
    assert 12 <= out["parallel"][1] <= 12 * 1.5


def test_a_chunk_is_decided_whole_only_where_every_pair_was_checked_and_kept_its_draft() -> None:
    rr = np.array([0, 0, 1, 1, 2, 2])
    tokens = np.array([7, 8, 1, 2, 4, 5])
    draft = np.array([7, 8, 1, 9, 4, 5])
    checked = np.array([0, 1, 2, 3, 4])  # the guard saw row 2's first pair only
    whole = kept_every_draft(rr, rr[checked], tokens[checked], draft[checked], 4)
    # row 0 kept both drafts; row 1 missed one; row 2 has an unchecked pair; row 3 sampled nothing
    np.testing.assert_array_equal(whole, [True, False, False, False])


def test_acceptance_stops_at_the_first_token_that_differs_from_its_draft() -> None:
    rr = np.array([0, 0, 0, 2, 2])
    cc = np.array([1, 3, 4, 0, 2])
    tokens = np.array([7, 8, 9, 1, 2])
    draft = np.array([7, 5, 9, 1, 2])
    # row 0: offset 3 differs (its inputs were right, so it is exact); row 1 sampled nothing; row 2 all
    np.testing.assert_array_equal(accepted(rr, cc, tokens, draft, 3), [3, -1, 2])


def test_the_guard_sees_the_drafted_states_of_the_predecessors_only() -> None:
    sc = straight_road_scene(num_agents=6, steps=40)
    eng = BatchEngine(tiny_checkpoint(), 2, SamplingConfig(guard=True))
    live = sc.valid[:, sc.current_index]
    eng.start_rows([0, 1], RowSpec(sc, 5, live), [1, 2])
    t = sc.current_index
    rr = np.array([0, 0, 0, 1, 1])
    who = np.array([0, 3, 1, 2, 4])  # acting order within each row
    draft = np.array([4, -1, 6, 9, 3])  # agent 3 of row 0 has no draft: it has not moved for anyone
    moved, after = guard_view(eng, rr, who, draft)
    known = eng.known[rr, :, t]
    np.testing.assert_array_equal(moved & ~known, _expected(rr, who, draft))
    # a predecessor's next state is its draft applied to its model state
    templates = eng.vocab.templates
    from trajeglish_env.geometry import to_global

    expect = to_global(eng.mxyh[0, 0, t], templates[eng.kind[0, 0], 4])
    np.testing.assert_allclose(after[1, 0], expect)  # pair 1 (agent 3) sees agent 0 moved
    np.testing.assert_allclose(after[4, 2], to_global(eng.mxyh[1, 2, t], templates[eng.kind[1, 2], 9]))


def _expected(rr: np.ndarray, who: np.ndarray, draft: np.ndarray) -> np.ndarray:
    """Per pair, the drafted agents that act before it in its row."""
    out = np.zeros((len(rr), 6), bool)
    for p in range(len(rr)):
        for q in range(p):
            if rr[q] == rr[p] and draft[q] >= 0:
                out[p, who[q]] = True
    return out


def test_the_look_ahead_is_taken_for_few_rows_of_subsets_mostly_to_draft() -> None:
    """Its positions (stepping rows x slots) stay within 256 times the share of slots it drafts: a
    24-agent env scene (23 NPCs) looks ahead up to 10 rows, subsets with 8 agents to draft up to 3."""
    from trajeglish_env.sampler.parallel import look_ahead_pays

    assert all(look_ahead_pays(rows, 24, 23 * rows) for rows in range(1, 11))
    assert not look_ahead_pays(11, 24, 23 * 11)
    assert all(look_ahead_pays(rows, 24, 8 * rows) for rows in (1, 2, 3))
    assert not look_ahead_pays(4, 24, 8 * 4)
    assert not look_ahead_pays(0, 24, 0)


@pytest.mark.parametrize(("rollouts", "looks"), [(1, True), (16, False)])
def test_a_scene_of_few_agents_looks_ahead_alone_only(rollouts: int, looks: bool) -> None:
    """2 agents in the tiny model's 6-slot context: one rollout looks ahead (6 positions for 2 drafts),
    16 do not (96 positions for 32: 96 x 96 > 256 x 32); the tokens are the sequential ones either way."""
    sc = straight_road_scene(num_agents=3, steps=40)  # the third enters late
    live = sc.valid[:, sc.current_index]
    assert live.sum() == 2
    out = {}
    for mode in ("sequential", "parallel"):
        cfg = SamplingConfig(seed=5, intra_step=mode)
        eng = RolloutEngine(tiny_checkpoint(), sc, rollouts, 8, live, config=cfg)
        eng.run()
        out[mode] = (eng.tokens.copy(), eng.look_ahead_calls)
    np.testing.assert_array_equal(out["parallel"][0], out["sequential"][0])
    assert out["sequential"][1] == 0
    assert (out["parallel"][1] > 0) == looks, out["parallel"][1]


@pytest.mark.parametrize("added", ["neighbour_input", "lane_input"])
@pytest.mark.parametrize("guard", [False, True])
def test_state_reading_models_look_ahead_from_drafted_states_exactly(added: str, guard: bool) -> None:
    """Models that read their step's states (neighbours, the road) look ahead too: the look-ahead positions
    read the next step's states as the drafts give them (parallel.drafted_next_step) and the states are
    put back, so parallel decoding still draws the sequential tokens and states, in fewer calls."""
    from helpers import extended_tiny_checkpoint

    ckpt = extended_tiny_checkpoint(added)
    sc = straight_road_scene(num_agents=6, steps=40)
    live = sc.valid[:, sc.current_index]
    out = {}
    for mode in ("sequential", "parallel"):
        cfg = SamplingConfig(seed=5, guard=guard, intra_step=mode, guard_road_ahead=0.0)
        eng = RolloutEngine(ckpt, sc, 1, 10, live, config=cfg)
        eng.run()
        calls = (eng.model_calls, eng.look_ahead_calls)
        out[mode] = (eng.tokens.copy(), eng.xyh.copy(), eng.valid.copy(), *calls)
    for i in range(3):
        np.testing.assert_array_equal(out["parallel"][i], out["sequential"][i])
    assert out["sequential"][4] == 0 and out["parallel"][4] >= 5, out["parallel"][4]
    assert out["parallel"][3] < out["sequential"][3]


def test_a_road_reading_model_decodes_a_real_womd_scene_in_a_batch_exactly() -> None:
    """The WOMD scene's 50 agents (several contexts), rows of a batch: parallel = sequential per row, with
    look-ahead calls where they pay."""
    from helpers import extended_tiny_checkpoint

    from trajeglish_env.sources.womd import read_womd

    sc = next(read_womd(womd_tfrecord()))
    live = sc.valid[:, sc.current_index]
    ckpt = extended_tiny_checkpoint("lane_input")
    out = {}
    for mode in ("sequential", "parallel"):
        eng = BatchEngine(ckpt, 2, SamplingConfig(intra_step=mode, prime_steps=3, guard=True))
        eng.start_rows([0, 1], RowSpec(sc, 6, live), [11, 12])
        eng.run()
        out[mode] = (eng.tokens.copy(), eng.mxyh.copy(), eng.look_ahead_calls)
    np.testing.assert_array_equal(out["parallel"][0], out["sequential"][0])
    np.testing.assert_array_equal(out["parallel"][1], out["sequential"][1])
    assert out["parallel"][2] > 0


def test_guarded_drafts_keep_a_step_at_about_one_call_where_the_guard_acts() -> None:
    """The shipped model's 24 NPCs of a SUMO scene where the guard's rules change draws (stalled riders set
    off, followers capped): the drafts are guarded draws and every pair of a call is guarded, so a changed
    draw does not cut the step short (91 calls in these 40 steps with unguarded drafts, 45 now), and the
    tokens stay the sequential ones."""
    from trajeglish_env.benchmark.measure import benchmark_scenes
    from trajeglish_env.checkpoint import load_pretrained

    sc = benchmark_scenes(24)[2]
    live = sc.valid[:, sc.current_index]
    out = {}
    for mode in ("sequential", "parallel"):
        config = SamplingConfig(intra_step=mode, compute_dtype="float32", temperature=0.75)
        eng = RolloutEngine(load_pretrained(), sc, 1, 40, live, config=config)
        eng.run()
        assert eng.guard is not None
        out[mode] = (eng.tokens.copy(), eng.model_calls, eng.guard.stats.masked)
    np.testing.assert_array_equal(out["parallel"][0], out["sequential"][0])
    assert out["sequential"][2] >= 30  # the guard changed draws
    assert out["parallel"][1] <= 40 * 1.25, out["parallel"][1]


def test_coupled_drafts_are_drawn_only_where_wanted_and_unchanged_there() -> None:
    """A step's drafts come from the look-ahead where it drafted; the coupled drafts (from the logits of the
    step before) are drawn only for the other agents, each from its own logits and number, so asking for
    fewer changes none of them."""
    from types import SimpleNamespace

    from trajeglish_env.sampler.parallel import coupled_drafts

    rng = np.random.default_rng(3)
    rs = SimpleNamespace(B=2, N=5, now=np.array([4, 7]), seed=np.array([11, 12]))
    logits = rng.normal(size=(2, 5, 64)).astype(np.float32)
    drawn_at = np.array([[3, 3, 2, 3, -1], [6, 6, 6, 6, 6]])
    every = coupled_drafts(rs, logits.copy(), drawn_at, 0.75, 1.0)  # type: ignore[arg-type]
    assert (every[0, [2, 4]] == -1).all() and (every[0, [0, 1, 3]] >= 0).all() and (every[1] >= 0).all()
    wanted = rng.random((2, 5)) < 0.5
    some = coupled_drafts(rs, logits.copy(), drawn_at, 0.75, 1.0, wanted)  # type: ignore[arg-type]
    np.testing.assert_array_equal(some, np.where(wanted, every, -1))
