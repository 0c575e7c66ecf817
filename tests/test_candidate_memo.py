"""The guard's per-agent memory of road-edge answers: measured once per key and entry, cleared when the agent
moves (or its slot holds another agent), grown with the rows."""

from __future__ import annotations

import numpy as np

from trajeglish_env.sampler.candidate_memo import KEY_WIDTH, CandidateMemo, memo_keys


def _keys(x: float, n: int = 1) -> np.ndarray:
    return memo_keys(np.tile([x, 2.0, 0.5], (n, 1)), np.tile([4.5, 2.0], (n, 1)), np.zeros(n), np.zeros(n), 3)


def test_entries_are_measured_once_until_the_key_changes() -> None:
    memo, asked = CandidateMemo(), []

    def measure(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        asked.append(len(i))
        return 100.0 * i + tokens[i, j]

    rows, agents = np.array([0, 1]), np.array([3, 0])
    tokens = np.array([[5, 7], [7, 9]])
    want = np.array([[True, True], [True, False]])
    got = memo.lookup(rows, agents, _keys(1.0, 2), tokens, want, measure, 16)
    np.testing.assert_array_equal(got, [[5.0, 7.0], [107.0, np.nan]])
    assert asked == [3]
    tokens = np.array([[7, 8], [9, 7]])  # two known, two new
    got = memo.lookup(rows, agents, _keys(1.0, 2), tokens, np.ones((2, 2), bool), measure, 16)
    np.testing.assert_array_equal(got, [[7.0, 8.0], [109.0, 107.0]])
    assert asked == [3, 2]
    moved = np.vstack([_keys(1.0), _keys(1.5)])  # the second agent moved: its answers are measured again
    got = memo.lookup(rows, agents, moved, tokens, np.ones((2, 2), bool), measure, 16)
    np.testing.assert_array_equal(got, [[7.0, 8.0], [109.0, 107.0]])
    assert asked == [3, 2, 2]
    assert memo.keys.shape[-1] == KEY_WIDTH


def test_a_slot_beyond_the_memory_grows_it_and_forgets() -> None:
    memo = CandidateMemo()
    one = np.ones((1, 1), bool)
    memo.lookup(np.array([0]), np.array([0]), _keys(0.0), np.array([[2]]), one, lambda i, j: i + 1.0, 4)
    assert memo.values.shape == (1, 1, 4)
    got = memo.lookup(np.array([3]), np.array([5]), _keys(0.0), np.array([[1]]), one, lambda i, j: i + 4.0, 4)
    assert got[0, 0] == 4.0 and memo.values.shape == (4, 6, 4)
    got = memo.lookup(np.array([0]), np.array([0]), _keys(0.0), np.array([[2]]), one, lambda i, j: i + 9.0, 4)
    assert got[0, 0] == 9.0  # measured again after the growth
