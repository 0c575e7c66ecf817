"""The compiled kernels of the guard's view of a pair (trajeglish_env/pair_kernels.py): the obstacles near
each agent, the following rule's caps, the stall rule's history, the wrong-way rule's lanes and the
candidates' verdicts equal the NumPy path's, call by call, on every call of guarded rollouts of a
bundled SUMO scene (with and without the escape rule) and on a crowd of boxes drawn on top of one
another; the supplied ego's lean tokenization equals the general tokenizer's."""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from helpers import bundle_scene

import trajeglish_env.guard_kernels as guard_kernels
import trajeglish_env.sampler.candidate_memo as candidate_memo
import trajeglish_env.sampler.engine as engine
import trajeglish_env.sampler.guard_ahead as guard_ahead
import trajeglish_env.sampler.guard_follow as guard_follow
import trajeglish_env.sampler.guard_geometry as guard_geometry
import trajeglish_env.sampler.guard_neighbours as guard_neighbours
import trajeglish_env.sampler.guard_stall as guard_stall
import trajeglish_env.sampler.lane_directions as lane_directions
import trajeglish_env.sampler.parallel as parallel
from trajeglish_env.compiled import pair_compiled
from trajeglish_env.sampler.lane_directions import LaneDirections

MODULES = (
    candidate_memo,
    guard_ahead,
    guard_follow,
    guard_geometry,
    guard_neighbours,
    guard_stall,
    lane_directions,
)
MODULES += (parallel,)


def _numpy(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` on the NumPy paths (the kernels switched off in every module that asks for them)."""
    with pytest.MonkeyPatch.context() as mp:
        for m in MODULES:
            mp.setattr(m, "pair_compiled", lambda: None)
        return fn(*args)


def _equal(got: Any, want: Any) -> None:
    got, want = (x if isinstance(x, tuple) else (x,) for x in (got, want))
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype and a.shape == b.shape


def _rollout_calls(escape: bool) -> dict[str, int]:
    """Guarded rollouts (shipped model, 2 rollouts x 30 steps) of a bundled SUMO scene: each call of the
    neighbours, following caps, stall history and lanes is answered by the kernels and by NumPy, compared."""
    from trajeglish_env.benchmark.workloads import benchmark_scenes
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.sampler import RolloutEngine, SamplingConfig

    assert pair_compiled() is not None, (
        "numba is a dependency of trajeglish_env: install it (pip install numba)"
    )
    counts: dict[str, int] = {}

    def spy(fn: Callable[..., Any], name: str, tally: Callable[[Any], dict[str, int]]) -> Callable[..., Any]:
        """``fn`` answered by the kernels and by NumPy, compared; its calls counted under ``name`` and what
        ``tally`` finds in its answers added up."""

        def both(*args: Any) -> Any:
            got = fn(*args)
            _equal(got, _numpy(fn, *args))
            for key, value in {name: 1, **tally(got)}.items():
                counts[key] = counts.get(key, 0) + value
            return got

        return both

    parts = ("collide", "escape", "off", "jump")
    spies = {
        (guard_geometry, "neighbours"): spy(
            guard_neighbours.neighbours, "neighbours", lambda g: {"near": int(g[2].sum())}
        ),
        (guard_geometry, "follow_caps"): spy(
            guard_follow.follow_caps, "follow", lambda g: {"capped": int(np.isfinite(g).sum())}
        ),
        (guard_geometry, "stalled"): spy(guard_stall.stalled, "stall", lambda g: {"stalled": int(g.sum())}),
        (LaneDirections, "against"): spy(LaneDirections.against, "lanes", lambda g: {}),
        (guard_geometry.GuardGeometry, "blocked_parts"): spy(
            guard_geometry.GuardGeometry.blocked_parts,
            "blocked",
            lambda g: {k: int(v.sum()) for k, v in zip(parts, g, strict=True)},
        ),
    }
    view = spy(parallel.guard_view, "view", lambda g: {"seen": int(g[0].sum())})
    spies.update({(parallel, "guard_view"): view, (engine, "guard_view"): view})
    sc = benchmark_scenes(24)[2]
    live = sc.valid[:, sc.current_index]
    config = SamplingConfig(temperature=1.0, guard_escape=escape)
    with pytest.MonkeyPatch.context() as mp:
        for (owner, name), wrapper in spies.items():
            mp.setattr(owner, name, wrapper)
        RolloutEngine(load_pretrained(), sc, 2, 30, live, config=config).run()
    return counts


@pytest.mark.parametrize("escape", [True, False])
def test_the_kernels_answer_every_call_of_guarded_rollouts_as_numpy_does(escape: bool) -> None:
    counts = _rollout_calls(escape)
    assert counts["neighbours"] >= 30 and counts["follow"] >= 30 and counts["lanes"] >= 30
    assert counts["near"] > 100 and counts["capped"] > 50  # agents near, and agents following others
    assert counts["stall"] >= 1 and counts["blocked"] >= 30 and counts["view"] >= 30 and counts["seen"] > 500
    assert counts["collide"] > 50 and counts["off"] > 50 and counts["jump"] > 50  # every rule masks some


def _crowd(n: int, agents: int, seed: int) -> tuple[Any, ...]:
    """``n`` pairs of rows of ``agents`` boxes drawn within a few metres of one another (many overlap now,
    some overlapped before they moved, some did not), as the guard's view of a step holds them."""
    rng = np.random.default_rng(seed)
    rr = np.arange(n)
    who = rng.integers(0, agents, n)
    tt = np.full(n, 1)
    xyh = np.zeros((n, agents, 3, 3))
    xyh[:, :, 1, :2] = rng.uniform(-6, 6, (n, agents, 2))
    xyh[:, :, 1, 2] = rng.uniform(-np.pi, np.pi, (n, agents))
    xyh[:, :, 2] = xyh[:, :, 1] + np.concatenate(
        [rng.uniform(-1.5, 1.5, (n, agents, 2)), rng.uniform(-0.3, 0.3, (n, agents, 1))], axis=2
    )
    valid = rng.random((n, agents, 3)) < 0.9
    size = np.column_stack([rng.uniform(0.5, 5.0, n * agents), rng.uniform(0.5, 2.2, n * agents)])
    rs = SimpleNamespace(
        valid=valid, xyh=xyh, size=size.reshape(n, agents, 2), row_external=rng.random((n, agents)) < 0.2
    )
    origin = xyh[rr, who, 1]
    own = rs.size[rr, who]
    extent = 3.0 + guard_geometry.half_diagonal(own)
    moved = rng.random((n, agents)) < 0.5
    state = np.where(moved[..., None] & valid[:, :, 2, None], xyh[:, :, 2], xyh[:, :, 1])
    present = (moved & valid[:, :, 2]) | (valid[:, :, 1] & ~moved)
    latest = (state, present, np.zeros((n, agents, 2)), moved)
    return rs, rr, who, tt, origin, own, extent, latest


@pytest.mark.parametrize("escape", [True, False])
def test_the_neighbours_of_a_crowd_equal_numpy(escape: bool) -> None:
    """Ties of distance included (boxes on one spot), the nearest first, the others padded as NumPy pads."""
    args = (*_crowd(400, 24, 11), escape)
    args[7][0][:50, :6] = args[7][0][:50, :1]  # six agents on one spot in 50 rows: equal distances
    got = guard_neighbours.neighbours(*args)
    want = _numpy(guard_neighbours.neighbours, *args)
    _equal(got, want)
    assert got[4].sum() > 100 and got[2].sum() > 1000  # tangled pairs, and many agents near
    assert (got[3].sum() > 20) == escape  # agents kept only to be escaped, with the rule


def test_following_caps_and_stalls_of_crowds_and_histories_equal_numpy() -> None:
    rng = np.random.default_rng(4)
    n, agents = 500, 16
    origin = np.column_stack([rng.uniform(-20, 20, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    state = origin[:, None] + np.concatenate(
        [rng.uniform(-30, 30, (n, agents, 2)), rng.normal(0, 0.3, (n, agents, 1))], axis=2
    )
    pace = rng.uniform(-0.2, 3.0, n)
    pace[:40] = np.nan
    pace[40:80] = 0.0
    turn = rng.normal(0, 0.05, n)
    args = (origin, rng.uniform(0.5, 5, (n, 2)), pace, turn, state, rng.uniform(0.5, 5, (n, agents, 2)))
    present, riders = rng.random((n, agents)) < 0.8, rng.random((n, agents)) < 0.9
    # boxes on the edge of the path, just inside and just outside it, straight ahead of riders heading east
    edge = np.arange(0, n, 5)
    origin[edge] = [0.0, 0.0, 0.0]
    turn[edge] = 0.0
    halves = (args[1][edge, 1, None] + args[5][edge, :, 1]) / 2 + guard_follow.FOLLOW_SIDE
    state[edge, :, 0] = rng.uniform(3, 30, (len(edge), agents))
    state[edge, :, 1] = halves + np.where(rng.random((len(edge), agents)) < 0.5, -1e-9, 1e-9)
    state[edge, :, 2] = 0.0
    velocity = rng.normal(0, 8, (n, agents, 2))
    caps = guard_follow.follow_caps(*args, present, velocity, riders, 3.0)
    _equal(caps, _numpy(guard_follow.follow_caps, *args, present, velocity, riders, 3.0))
    assert 100 < np.isfinite(caps).sum() < n
    # histories: drive, stand for a while, perhaps set off; gaps and a step not reached yet
    T = 40
    speed = np.where(rng.random((n, T)) < 0.5, 0.0, rng.uniform(0, 1.5, (n, T)))
    speed[:, 10:25] *= rng.random((n, 1)) < 0.5
    heading = rng.uniform(-np.pi, np.pi, (n, 1))
    xy = np.cumsum(speed[..., None] * np.stack([np.cos(heading), np.sin(heading)], -1), axis=1)
    mxyh = np.concatenate([xy, np.broadcast_to(heading[..., None], (n, T, 1))], axis=2)
    valid = rng.random((n, T)) < 0.97
    t = rng.integers(1, T, n)
    for steps in (1, 5, 10):
        got = guard_stall.stalled(mxyh, valid, t, steps)
        _equal(got, _numpy(guard_stall.stalled, mxyh, valid, t, steps))
        assert 0 < got.sum() < n
    # every run length and every wait after it, to the limits of the rule: drive 5 steps, stand `run` steps
    run, wait = (a.ravel() for a in np.meshgrid(np.arange(1, 13), np.arange(0, 26)))
    moves = np.zeros((len(run), T))
    moves[:, 1:6] = 1.0
    moves[np.arange(T)[None] > 5 + run[:, None]] = 0.3  # sets off again after the run (when it is reached)
    xy = np.stack([np.cumsum(moves, axis=1), np.zeros((len(run), T))], -1)
    mxyh = np.concatenate([xy, np.zeros((len(run), T, 1))], axis=2)
    valid = np.ones((len(run), T), bool)
    for steps in (3, 8):
        got = guard_stall.stalled(mxyh, valid, 5 + run + wait, steps)
        _equal(got, _numpy(guard_stall.stalled, mxyh, valid, 5 + run + wait, steps))
        expect = (run >= steps) & (wait == 0)  # standing still at t: stalled once the run is long enough
        np.testing.assert_array_equal(got[wait == 0], expect[wait == 0])
        assert got.sum() > 10 and (~got).sum() > 10


def test_lanes_against_off_the_grid_and_at_every_heading_equal_numpy() -> None:
    sc = bundle_scene("sumo-random-999000-0-0")
    lanes = LaneDirections.of(sc)
    assert lanes is not None
    rng = np.random.default_rng(2)
    ny, nx = lanes.masks.shape
    m = 50000
    xy = rng.uniform(
        [lanes.x0 - 5, lanes.y0 - 5], [lanes.x0 + nx * lanes.cell + 5, lanes.y0 + ny * lanes.cell + 5], (m, 2)
    )
    xyh = np.column_stack([xy, rng.uniform(-4 * np.pi, 4 * np.pi, m)]).reshape(100, 500, 3)
    xyh[0, :5, 0] = np.nan
    got = lanes.against(xyh)
    with np.errstate(invalid="ignore"):
        want = _numpy(lanes.against, xyh)
    _equal(got, want)
    assert 0.01 < got.mean() < 0.5


def test_the_kernels_are_off_with_the_guard_kernels() -> None:
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(guard_kernels, "AVAILABLE", False)
        assert pair_compiled() is None
    assert pair_compiled() is not None


def test_a_supplied_move_tokenizes_as_the_general_tokenizer_does() -> None:
    """tokenize_moves (an env's supplied egos) against tokenize of the same two-step tracks: vehicles,
    pedestrians and cyclists of a SUMO scene at every logged step."""
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.tokenizer.tokenize import tokenize, tokenize_moves

    vocab = load_pretrained().vocabulary
    sc = bundle_scene("sumo-random-999000-0-1")
    a, t = np.nonzero(sc.valid[:, :-1] & sc.valid[:, 1:])
    base = sc.xyh[a, t] + np.random.default_rng(0).normal(0, 0.05, (len(a), 3))  # a model's view, off the log
    target = sc.xyh[a, t + 1]
    tokens, states, error = tokenize_moves(vocab, base, target, sc.size[a], sc.kind[a].astype(np.int64))
    ref = tokenize(
        vocab,
        np.stack([base, target], 1)[:, None],
        np.ones((len(a), 1, 2), bool),
        sc.size[a][:, None],
        sc.kind[a].astype(np.int64)[:, None],
    )
    np.testing.assert_array_equal(tokens, ref.tokens[:, 0, 0])
    np.testing.assert_array_equal(states, ref.xyh[:, 0, 1])
    np.testing.assert_array_equal(error, ref.error[:, 0, 1])
    assert len(np.unique(sc.kind[a])) >= 2 and len(a) > 500


def test_a_non_finite_supplied_state_is_refused_naming_the_agent() -> None:
    from trajeglish_env.benchmark.workloads import benchmark_scenes
    from trajeglish_env.env import raw_env

    env = raw_env([benchmark_scenes(24)[0]])
    env.reset(seed=0)
    eng = env.batch.rows.engine
    (ego,) = np.flatnonzero(eng.row_external[0])
    with pytest.raises(
        ValueError, match=r"supplied state of external vehicle_\d+ .* expected finite x, y, heading"
    ):
        eng.supply(np.array([0]), np.array([ego]), np.array([[np.nan, 0.0, 0.0]]))


def test_the_verdicts_on_a_crowd_equal_numpy() -> None:
    """Every rule without a map at once on synthetic pairs: obstacles to avoid and to escape, following
    caps, departures under the green and the stall rule, speed changes; the shipped vehicle templates."""
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.edge_cells import EdgeCells
    from trajeglish_env.sampler.guard_edges import RoadView

    templates = load_pretrained().vocabulary.templates
    geometry = guard_geometry.GuardGeometry(templates, step_change=0.8, stall_steps=5, follow_decel=3.0)
    rng = np.random.default_rng(8)
    n, k = 300, 6
    origin = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    near = origin[:, None] + np.concatenate(
        [rng.uniform(-5, 5, (n, k, 2)), rng.normal(0, 1, (n, k, 1))], axis=2
    )
    pace = rng.uniform(0, 2.5, n)
    pace[:30] = np.nan
    edges = RoadView(np.zeros(n, bool), np.zeros(n), np.full(n, -1), np.zeros(n, np.int64), EdgeCells(), ())  # type: ignore[arg-type]
    pairs = guard_geometry.Pairs(
        *(np.zeros(n, np.int64), np.arange(n), np.ones(n, np.int64), origin, rng.uniform(1, 5, (n, 2))),
        *(np.zeros(n, np.int64), np.full(n, 4.0), near, rng.uniform(0.5, 5, (n, k, 2))),
        *(rng.random((n, k)) < 0.7, rng.random((n, k)) < 0.3, edges, np.zeros(n, bool)),
        *(rng.random(n) < 0.2, {}, pace, rng.random(n) < 0.2, np.zeros(n, bool), {}),
        *(np.where(rng.random(n) < 0.5, rng.uniform(0, 2, n), np.inf), np.zeros((n, 8))),
    )
    sel = rng.permutation(n)[:250]
    tokens = rng.integers(0, templates.shape[1], (250, 40))
    got = geometry.blocked_parts(pairs, sel, tokens)
    want = _numpy(geometry.blocked_parts, pairs, sel, tokens)
    _equal(got, want)
    for part in got:
        assert 100 < part.sum() < part.size - 100


def _memo_run(numpy_path: bool) -> tuple[list[np.ndarray], list[tuple[np.ndarray, ...]], Any]:
    """60 lookups of a candidate memory (slots whose keys change or stay, entries wanted or not, repeated
    entries) answered from a table of truths: the answers, the measurements asked for, the memory."""
    from trajeglish_env.sampler.candidate_memo import KEY_WIDTH, CandidateMemo

    rng = np.random.default_rng(12)
    truth = rng.normal(size=(4, 10, 3, 50))  # the answer of (row, agent, key version, entry)
    memo, answers, asked = CandidateMemo(), [], []
    version = np.zeros((4, 10), np.int64)
    for _ in range(60):
        m = int(rng.integers(1, 12))
        slots = rng.permutation(40)[:m]
        rows, agents = slots // 10, slots % 10
        change = rng.random(m) < 0.3
        version[rows[change], agents[change]] = (version[rows[change], agents[change]] + 1) % 3
        keys = np.repeat(version[rows, agents][:, None], KEY_WIDTH, axis=1).astype(np.float64)
        entries = rng.integers(0, 50, (m, 7))
        want = rng.random((m, 7)) < 0.8
        at = (rows, agents, version[rows, agents])

        def measure(
            i: np.ndarray, j: np.ndarray, at: tuple = at, entries: np.ndarray = entries
        ) -> np.ndarray:  # type: ignore[type-arg]
            asked.append((i.copy(), j.copy()))
            return truth[at[0][i], at[1][i], at[2][i], entries[i, j]]

        lookup = (rows, agents, keys, entries, want, measure, 50)
        got = _numpy(memo.lookup, *lookup) if numpy_path else memo.lookup(*lookup)
        expect = np.where(want, truth[rows[:, None], agents[:, None], at[2][:, None], entries], np.nan)
        np.testing.assert_array_equal(got, expect)
        answers.append(got)
    return answers, asked, memo


def test_the_candidate_memory_answers_and_keeps_as_numpy_does() -> None:
    """The compiled memory (pair_kernels.memo_gather) against the NumPy one: the same answers (the truths),
    the same measurements asked for, the same memory afterwards."""
    (got, got_asked, got_memo), (want, want_asked, want_memo) = _memo_run(False), _memo_run(True)
    for a, b in zip(got, want, strict=True):
        _equal(a, b)
    assert len(got_asked) == len(want_asked) > 20
    for a, b in zip(got_asked, want_asked, strict=True):
        _equal(a, b)
    _equal((got_memo.keys, got_memo.values), (want_memo.keys, want_memo.values))


def test_kept_up_poses_equal_numpy() -> None:
    """Arcs and straight lines (a turn under 1e-6 rad), standing and creeping motions (the step cap), from
    poses all round the circle: the poses of guard_ahead.kept_up, number for number."""
    from trajeglish_env.pair_kernels import kept_up_poses
    from trajeglish_env.sampler.guard_ahead import kept_up

    rng = np.random.default_rng(6)
    n = 5000
    origin = np.column_stack([rng.uniform(-500, 500, (n, 2)), rng.uniform(-4, 4, n)])
    step = np.column_stack([rng.uniform(-0.5, 3.5, n), rng.normal(0, 0.2, n), rng.normal(0, 0.05, n)])
    step[:500, 2] = rng.uniform(-1e-6, 1e-6, 500)  # straight
    step[500:700, :2] = rng.uniform(-1e-3, 1e-3, (200, 2))  # creeping: AHEAD_MOST_STEPS steps
    step[700:750] = 0.0
    distance = np.array([7.5, 15.0, 30.0])
    got = np.empty((n, 3, 3))
    kept_up_poses(origin, step, distance, got)
    _equal(got, kept_up(origin[:, None], step[:, None], distance))
