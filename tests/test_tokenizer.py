"""Tokenizer core: corner distance, exact nearest search, tokenize/render, gaps, invariances, noise, bad input
(the paper's Sec. 3.1 and appendix "Regularization")."""

from __future__ import annotations

import numpy as np
import pytest

from trajeglish_env.geometry import to_global, wrap_angle
from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer import (
    MotionVocabulary,
    NoiseConfig,
    TokenizeError,
    corner_distance,
    render,
    tokenize,
)
from trajeglish_env.tokenizer.distance import mean_square_corner_distance
from trajeglish_env.tokenizer.kdisks import sample_kdisks
from trajeglish_env.tokenizer.nearest import SearchTable, brute_force_nearest, nearest_templates
from trajeglish_env.tokenizer.synthetic import synthetic_trajectories

ALL_KINDS = tuple(AgentKind)


@pytest.fixture(scope="module")
def vocab() -> MotionVocabulary:
    """A small k-disks vocabulary (V=256) fitted per class on synthetic trajectories."""
    rng = np.random.default_rng(0)
    xyh, valid, _, kind = synthetic_trajectories(1500, 60, rng, kinds=ALL_KINDS)
    from trajeglish_env.geometry import to_local

    per_kind = []
    for k in ALL_KINDS:
        rows = kind == int(k)
        trans = to_local(xyh[rows, :-1], xyh[rows, 1:]).reshape(-1, 3)
        per_kind.append(sample_kdisks(trans, 256, 0.035, np.random.default_rng(int(k))))
    return MotionVocabulary(np.stack(per_kind), method="k-disks")


@pytest.fixture(scope="module")
def trajectories() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return synthetic_trajectories(60, 40, np.random.default_rng(1), kinds=ALL_KINDS)


# ---------------------------------------------------------------- corner distance
def test_corner_distance_known_values() -> None:
    size = np.array([4.0, 2.0])
    a = np.array([1.0, 2.0, 0.3])
    assert corner_distance(a, a, size) == 0.0
    assert corner_distance(a, a + [0.3, 0.4, 0.0], size) == pytest.approx(0.5)
    # Half a turn about the centre sends every corner to the opposite one: distance = the diagonal.
    assert corner_distance(a, a + [0.0, 0.0, np.pi], size) == pytest.approx(np.hypot(4.0, 2.0))
    # The mean *squared* distance has the closed form |u|^2 + (l^2 + w^2) sin^2(dh / 2).
    rng = np.random.default_rng(2)
    p, q = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    s = rng.uniform(0.5, 6, (50, 2))
    from trajeglish_env.geometry import box_corners

    sq = ((box_corners(p, s) - box_corners(q, s)) ** 2).sum(-1).mean(-1)
    np.testing.assert_allclose(mean_square_corner_distance(p, q, (s**2).sum(-1)), sq, rtol=1e-12)
    l2 = np.linalg.norm(box_corners(p, s) - box_corners(q, s), axis=-1).mean(-1)
    np.testing.assert_allclose(corner_distance(p, q, s), l2, rtol=1e-12)
    assert (l2 <= np.sqrt(sq) + 1e-12).all() and (l2 >= np.sqrt(sq / 2) - 1e-12).all()


# ---------------------------------------------------------------- exact nearest search
@pytest.mark.parametrize("spread", [0.002, 0.05])
def test_nearest_matches_brute_force(vocab: MotionVocabulary, spread: float) -> None:
    rng = np.random.default_rng(3)
    templates = vocab.for_kind(AgentKind.VEHICLE)
    local = templates[rng.integers(len(templates), size=6000)] + rng.normal(0, spread, (6000, 3)) * [
        1,
        1,
        0.2,
    ]
    size = np.stack([rng.uniform(0.3, 18, 6000), rng.uniform(0.3, 3, 6000)], 1)
    table = SearchTable.build(templates)
    ref_index, ref_dist = brute_force_nearest(templates, local, size)
    # Default blocks/window, tiny windows (most rows retried over all templates), and threads.
    for kwargs in ({}, {"block": 100, "window": 0.005}, {"block": 700, "threads": 2}):
        index, dist = nearest_templates(table, local, size, **kwargs)  # type: ignore[arg-type]
        np.testing.assert_array_equal(index, ref_index)
        np.testing.assert_array_equal(dist, ref_dist)


def test_nearest_breaks_ties_to_lowest_index() -> None:
    templates = np.array([[1.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    index, dist = nearest_templates(
        SearchTable.build(templates[[0, 2, 1]]), np.array([[0.5, 0.01, 0.0]]), np.array([[4.0, 2.0]])
    )
    assert index.tolist() == [1] and dist[0] == pytest.approx(0.01)


# ---------------------------------------------------------------- tokenize / render
def test_round_trip_and_error(vocab: MotionVocabulary, trajectories) -> None:  # type: ignore[no-untyped-def]
    xyh, valid, size, kind = trajectories
    tok = tokenize(vocab, xyh, valid, size, kind)
    assert tok.tokens.shape == (60, 39) and tok.tokens.dtype == np.int64
    assert (tok.tokens >= 0).all() and (tok.tokens < vocab.size).all()
    rendered, ok = render(vocab, tok.tokens, kind, xyh[:, 0])
    assert ok.all()
    np.testing.assert_allclose(rendered, tok.xyh, atol=1e-9)
    err = corner_distance(rendered, xyh, size[:, None, :])
    np.testing.assert_allclose(err, tok.error, atol=1e-9)
    assert err[:, 0].max() == 0.0  # the first state is the logged one
    # Most steps are tokenized to within a few cm (V=256 fitted on other synthetic agents).
    assert np.median(err[:, 1:]) < 0.03 and (err[:, 1:] < 0.05).mean() > 0.8
    # Each token is the argmin from the tokenized state (checked by brute force for one step).
    from trajeglish_env.geometry import to_local

    t = 20
    for k in ALL_KINDS:
        rows = kind == int(k)
        local = to_local(tok.xyh[rows, t], xyh[rows, t + 1])
        ref, _ = brute_force_nearest(vocab.for_kind(k), local, size[rows])
        np.testing.assert_array_equal(tok.tokens[rows, t], ref)


def test_invariant_to_global_frame_and_time_shift(vocab: MotionVocabulary, trajectories) -> None:  # type: ignore[no-untyped-def]
    xyh, valid, size, kind = trajectories
    tok = tokenize(vocab, xyh, valid, size, kind)
    frame = np.array([1234.5, -987.25, 2.1])
    moved = to_global(np.broadcast_to(frame, xyh.shape), xyh)
    tok_moved = tokenize(vocab, moved, valid, size, kind)
    np.testing.assert_array_equal(tok_moved.tokens, tok.tokens)
    np.testing.assert_allclose(tok_moved.error, tok.error, atol=1e-9)
    shift = 7
    shifted = np.concatenate([np.zeros((60, shift, 3)), xyh], 1)
    shifted_valid = np.concatenate([np.zeros((60, shift), bool), valid], 1)
    tok_shift = tokenize(vocab, shifted, shifted_valid, size, kind)
    np.testing.assert_array_equal(tok_shift.tokens[:, shift:], tok.tokens)
    assert (tok_shift.tokens[:, :shift] == -1).all()
    np.testing.assert_array_equal(tok_shift.error[:, shift:], tok.error)


def test_batch_dimensions_match_flat(vocab: MotionVocabulary, trajectories) -> None:  # type: ignore[no-untyped-def]
    xyh, valid, size, kind = trajectories
    flat = tokenize(vocab, xyh, valid, size, kind)
    batched = tokenize(
        vocab,
        xyh.reshape(3, 20, 40, 3),
        valid.reshape(3, 20, 40),
        size.reshape(3, 20, 2),
        kind.reshape(3, 20),
    )
    np.testing.assert_array_equal(batched.tokens.reshape(60, 39), flat.tokens)
    np.testing.assert_array_equal(batched.xyh.reshape(60, 40, 3), flat.xyh)


def test_gaps_are_anchored_and_flagged(vocab: MotionVocabulary, trajectories) -> None:  # type: ignore[no-untyped-def]
    xyh, valid, size, kind = trajectories
    valid = valid.copy()
    valid[0, :5] = False  # appears at step 5
    valid[1, 10:14] = False  # gap, reappears at step 14
    valid[2, 30:] = False  # disappears at step 30
    xyh = xyh.copy()
    xyh[1, 10:14] = np.nan  # invalid states may hold anything
    tok = tokenize(vocab, xyh, valid, size, kind)
    assert (tok.tokens[0, :5] == -1).all() and (tok.tokens[0, 5:] >= 0).all()
    assert (tok.tokens[1, 9:14] == -1).all() and tok.tokens[1, 14] >= 0 and tok.tokens[1, 8] >= 0
    assert (tok.tokens[2, 29:] == -1).all() and tok.tokens[2, 28] >= 0
    assert tok.anchored[0].nonzero()[0].tolist() == [5]
    assert tok.anchored[1].nonzero()[0].tolist() == [0, 14]
    np.testing.assert_array_equal(tok.xyh[1, 14], xyh[1, 14])
    assert np.isnan(tok.xyh[1, 10:14]).all() and np.isnan(tok.error[1, 10:14]).all()
    assert tok.error[1, 14] == 0.0
    assert tok.steps_since_anchor[1, 13] == -1 and tok.steps_since_anchor[1, 16] == 2
    rendered, ok = render(vocab, tok.tokens, kind, anchor_xyh=xyh, anchored=tok.anchored)
    np.testing.assert_array_equal(ok, valid)
    np.testing.assert_allclose(rendered[valid], tok.xyh[valid], atol=1e-9)
    # Without anchors, a -1 token ends the rendered agent.
    _, ok_plain = render(vocab, tok.tokens, kind, np.where(valid[:, :1], xyh[:, 0], np.nan))
    assert not ok_plain[1, 14:].any() and not ok_plain[0].any()


# ---------------------------------------------------------------- noisy tokenization
def test_noise_zero_sigma_gives_argmin(vocab: MotionVocabulary, trajectories) -> None:  # type: ignore[no-untyped-def]
    xyh, valid, size, kind = trajectories
    plain = tokenize(vocab, xyh, valid, size, kind)
    for sigma in (0.0, 1e-7):
        noisy = tokenize(
            vocab, xyh, valid, size, kind, noise=NoiseConfig(sigma, 0.95), rng=np.random.default_rng(0)
        )
        np.testing.assert_array_equal(noisy.input_tokens, plain.tokens)
        np.testing.assert_array_equal(noisy.tokens, plain.tokens)
    noisy = tokenize(
        vocab, xyh, valid, size, kind, noise=NoiseConfig(0.008, 0.95), rng=np.random.default_rng(0)
    )
    np.testing.assert_array_equal(noisy.tokens, plain.tokens)  # targets stay the argmin
    np.testing.assert_array_equal(noisy.xyh, plain.xyh)
    changed = (noisy.input_tokens != noisy.tokens).mean()
    assert 0.05 < changed < 0.95
    again = tokenize(
        vocab, xyh, valid, size, kind, noise=NoiseConfig(0.008, 0.95), rng=np.random.default_rng(0)
    )
    np.testing.assert_array_equal(again.input_tokens, noisy.input_tokens)


@pytest.mark.parametrize("top_p", [1.0, 0.95, 0.6])
def test_noise_matches_softmax_nucleus(vocab: MotionVocabulary, top_p: float) -> None:
    """Empirical token frequencies for one transition match softmax(-d/sigma) after the nucleus cut."""
    sigma, n = 0.008, 40000
    templates = vocab.for_kind(AgentKind.VEHICLE)
    size = np.array([4.6, 1.9])
    # Between two neighbouring templates, so that several templates have sizeable probability.
    gap = corner_distance(templates, templates[5], size)
    gap[5] = np.inf
    target = 0.5 * (templates[5] + templates[np.argmin(gap)]) + np.array([0.0, 0.004, 0.0])
    d = corner_distance(templates, target, size)
    p = np.exp(-(d - d.min()) / sigma)
    p /= p.sum()
    order = np.lexsort((np.arange(len(d)), d))
    cum = np.cumsum(p[order])
    keep = order[: int(np.searchsorted(cum, top_p) + 1)] if top_p < 1 else order
    expected = np.zeros_like(p)
    expected[keep] = p[keep] / p[keep].sum()
    xyh = np.zeros((n, 2, 3))
    xyh[:, 1] = target
    tok = tokenize(
        vocab,
        xyh,
        np.ones((n, 2), bool),
        np.tile(size, (n, 1)),
        np.zeros(n, np.int8),
        noise=NoiseConfig(sigma, top_p),
        rng=np.random.default_rng(5),
    )
    assert (tok.tokens == np.argmin(d)).all()
    freq = np.bincount(tok.input_tokens[:, 0], minlength=len(d)) / n
    assert set(np.flatnonzero(freq)) <= set(keep.tolist())
    assert np.abs(freq - expected).max() < 4 * np.sqrt(expected.max() / n) + 1e-3
    assert expected.max() < 0.9  # the test is not trivial: several templates are likely


# ---------------------------------------------------------------- bad input
def test_bad_input_is_rejected_clearly(vocab: MotionVocabulary, trajectories) -> None:  # type: ignore[no-untyped-def]
    xyh, valid, size, kind = trajectories
    bad = xyh.copy()
    bad[3, 7, 1] = np.nan
    with pytest.raises(TokenizeError, match="agent 3, step 7"):
        tokenize(vocab, bad, valid, size, kind)
    zero = size.copy()
    zero[4] = [4.0, 0.0]
    with pytest.raises(TokenizeError, match="size: agent 4"):
        tokenize(vocab, xyh, valid, zero, kind)
    with pytest.raises(TokenizeError, match=r"xyh: expected an array \[..., N, T, 3\]"):
        tokenize(vocab, xyh[..., :2], valid, size, kind)
    with pytest.raises(TokenizeError, match="valid: expected shape"):
        tokenize(vocab, xyh, valid[:, :-1], size, kind)
    with pytest.raises(TokenizeError, match="valid: expected dtype bool"):
        tokenize(vocab, xyh, valid.astype(int), size, kind)
    with pytest.raises(TokenizeError, match="kind: expected integer AgentKind"):
        tokenize(vocab, xyh, valid, size, np.full(60, 7))
    with pytest.raises(TokenizeError, match="size: expected shape"):
        tokenize(vocab, xyh, valid, size[:, :1], kind)
    with pytest.raises(TokenizeError, match="rng"):
        tokenize(vocab, xyh, valid, size, kind, noise=NoiseConfig())
    with pytest.raises(TokenizeError, match="tokens: values must be"):
        render(vocab, np.full((2, 3), vocab.size), np.zeros(2, int), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="sigma"):
        NoiseConfig(sigma=-1.0)
    # Invalid steps may hold NaN without complaint.
    ok = xyh.copy()
    ok[5, 3] = np.nan
    v = valid.copy()
    v[5, 3] = False
    assert tokenize(vocab, ok, v, size, kind).tokens[5, 2] == -1


def test_wrap_angle_of_tokenized_heading(vocab: MotionVocabulary) -> None:
    """Headings near +-pi tokenize like any other (no jump of 2 pi in the local frame)."""
    n, steps = 4, 30
    heading = np.pi - 0.02 + 0.004 * np.arange(steps)
    xyh = np.zeros((n, steps, 3))
    xyh[..., 0] = np.cumsum(np.cos(heading)) * 1.0
    xyh[..., 1] = np.cumsum(np.sin(heading)) * 1.0
    xyh[..., 2] = wrap_angle(heading)
    tok = tokenize(vocab, xyh, np.ones((n, steps), bool), np.tile([4.5, 2.0], (n, 1)), np.zeros(n, int))
    assert np.nanmax(tok.error) < 0.1
