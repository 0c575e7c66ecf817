"""The guard's pairs and draws kept within a step (``sampler.pair_memo``): taken only from the same view,
equal field by field to pairs computed anew, and nothing sampled or counted changes."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from trajeglish_env.sampler import RolloutEngine, SamplingConfig
from trajeglish_env.sampler.guard_geometry import GuardGeometry, Pairs
from trajeglish_env.sampler.pair_memo import NEAR_FILL, StepDraws, StepPairs, view_key


def _view(n: int = 2, agents: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    moved = np.zeros((n, agents), bool)
    moved[:, 1] = True
    after = np.arange(n * agents * 3, dtype=float).reshape(n, agents, 3)
    return view_key(moved, after, np.ones((n, agents), bool))


def test_a_pair_is_taken_only_from_the_same_view_step_and_cells() -> None:
    memo = StepPairs()
    kept = SimpleNamespace(rows=np.array([0, 0]), agents=np.array([2, 3]), t=np.array([7, 7]))
    key = _view()
    memo.record(kept, key, (1, 4), epoch=5)
    rr, who, tt = np.array([0, 0]), np.array([2, 3]), np.array([7, 7])
    np.testing.assert_array_equal(memo.match(rr, who, tt, key, (1, 4), 5), [0, 1])
    flipped = tuple(a[::-1] for a in key)  # asked in another order
    np.testing.assert_array_equal(memo.match(rr, who[::-1], tt, flipped, (1, 4), 5), [1, 0])
    moved, after, valid = (a.copy() for a in key)
    after[0, 0] += 1.0  # an agent that has not moved: its next state is never read
    np.testing.assert_array_equal(memo.match(rr, who, tt, view_key(moved, after, valid), (1, 4), 5), [0, 1])
    after[1, 1, 2] += 1e-9  # a moved agent's next state differs: that pair is computed anew
    np.testing.assert_array_equal(memo.match(rr, who, tt, view_key(moved, after, valid), (1, 4), 5), [0, -1])
    moved[0, 2] = True  # another agent counts as moved
    np.testing.assert_array_equal(memo.match(rr, who, tt, view_key(moved, after, valid), (1, 4), 5), [-1, -1])
    assert (memo.match(rr, who, tt + 1, key, (1, 4), 5) == -1).all()  # another step
    assert (memo.match(rr, who, tt, key, (1, 4), 6) == -1).all()  # other road cells
    one = tuple(a[:1] for a in key)
    assert (memo.match(np.array([0]), np.array([1]), np.array([7]), one, (1, 4), 5) == -1).all()  # not kept
    memo.clear()
    assert (memo.match(rr, who, tt, key, (1, 4), 5) == -1).all()


def test_a_draw_is_kept_only_where_it_stood_from_the_same_view() -> None:
    draws = StepDraws()
    rr, who = np.array([0, 0, 1]), np.array([0, 1, 1])
    draws.record(rr, who, np.array([5, 6, 7]), np.array([True, False, True]), (2, 3))
    hits = np.array([True, True, False])
    np.testing.assert_array_equal(draws.kept(rr, who, np.array([5, 6, 7]), hits), [True, False, False])
    np.testing.assert_array_equal(draws.kept(rr, who, np.array([4, 6, 7]), np.ones(3, bool)), [0, 0, 1])


def _padded(a: np.ndarray, k: int, fill: object) -> np.ndarray:
    return np.pad(a, [(0, 0), (0, k - a.shape[1])] + [(0, 0)] * (a.ndim - 2), constant_values=fill)


def _assert_same_pairs(got: Pairs, fresh: Pairs) -> None:
    """Every field of ``got`` equals ``fresh``'s; of the near obstacles, the real ones (no rule reads the
    others, and a memory's rows may be padded to more of them)."""
    k = max(got.near_xyh.shape[1], fresh.near_xyh.shape[1])
    real = _padded(fresh.near_real, k, False)
    np.testing.assert_array_equal(_padded(got.near_real, k, False), real)
    for f in dataclasses.fields(Pairs):
        a, b = getattr(got, f.name), getattr(fresh, f.name)
        if f.name in NEAR_FILL:
            a, b = _padded(a, k, NEAR_FILL[f.name])[real], _padded(b, k, NEAR_FILL[f.name])[real]
        if f.name == "edges":
            for name in ("road", "limit", "maps", "rows"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        elif f.name in ("signals", "lanes"):
            assert all(a[r] is b[r] for r in b), f.name
        else:
            np.testing.assert_array_equal(a, b, err_msg=f.name)


def _guarded_run(mode: str) -> tuple[np.ndarray, dict[str, int], dict[str, int]]:
    """The shipped model's 24 NPCs of a SUMO scene where the guard's rules change draws, 30 parallel steps:
    tokens, the guard's counters, and how often the memory served (``mode`` "anew": as if it never did;
    "kept": each pair it gave checked against a fresh computation)."""
    from trajeglish_env.benchmark.measure import benchmark_scenes
    from trajeglish_env.checkpoint import load_pretrained

    sc = benchmark_scenes(24)[2]
    live = sc.valid[:, sc.current_index]
    served = {"pairs": 0, "kept pairs": 0, "draws": 0, "kept draws": 0}
    recall, kept = GuardGeometry.recall, StepDraws.kept

    def checked_recall(self, rs, rr, who, tt, view=None):  # type: ignore[no-untyped-def]
        pairs, hits = recall(self, rs, rr, who, tt, view)
        if mode == "anew":
            hits = np.zeros(len(rr), bool)
        elif hits.any():  # what the memory gave is what a fresh computation gives
            _assert_same_pairs(pairs, self._fresh_pairs(rs, rr, who, tt, view))
        served["pairs"] += len(rr)
        served["kept pairs"] += int(hits.sum())
        return pairs, hits

    def counted_kept(self, rr, who, tokens, hits):  # type: ignore[no-untyped-def]
        got = kept(self, rr, who, tokens, hits)
        served["draws"] += len(rr)
        served["kept draws"] += int(got.sum())
        return got

    config = SamplingConfig(compute_dtype="float32", temperature=0.75)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(GuardGeometry, "recall", checked_recall)
        mp.setattr(StepDraws, "kept", counted_kept)
        eng = RolloutEngine(load_pretrained(), sc, 1, 30, live, config=config)
        eng.run()
    assert eng.guard is not None
    return eng.tokens.copy(), dataclasses.asdict(eng.guard.stats), served


def test_kept_pairs_and_draws_change_no_token_and_no_count() -> None:
    kept, anew = _guarded_run("kept"), _guarded_run("anew")
    np.testing.assert_array_equal(kept[0], anew[0])
    assert kept[1] == anew[1]  # the guard's counters: sampled, guarded, masked, fallbacks
    assert anew[1]["masked"] > 0  # the guard changed draws in this scene
    served = kept[2]
    assert anew[2]["kept pairs"] == anew[2]["kept draws"] == 0
    # of every pair guarded (the drafts' pass's too, which find nothing kept), a fifth or more are taken
    # from the memory, and most of those keep their draws (373 and 346 of 1,504 when written)
    assert served["kept pairs"] >= 0.2 * served["pairs"], served
    assert served["kept draws"] >= 0.15 * served["draws"], served
