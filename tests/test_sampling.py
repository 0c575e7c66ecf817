"""Sampling with temperature/nucleus, and greedy closed-loop decoding through the engine's cache."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import record_encoded, straight_road_scene, tiny_checkpoint

from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.sampler.sampling import (
    counter_uniform,
    draft_draws,
    nucleus_mask,
    sample_from_probs,
    sample_with_uniform,
    token_probs,
)


def test_temperature_zero_is_argmax_and_small_temperature_approaches_it() -> None:
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(50, 7, generator=g)
    u = counter_uniform(np.full(50, 1, np.uint64), np.arange(50), np.zeros(50))
    assert np.array_equal(sample_with_uniform(logits, 0.0, 1.0, u), logits.argmax(-1).numpy())
    assert np.array_equal(sample_with_uniform(logits, 1e-4, 1.0, u), logits.argmax(-1).numpy())
    with pytest.raises(ValueError, match="temperature must be >= 0"):
        sample_with_uniform(logits, -1.0, 1.0, u)


def test_nucleus_keeps_the_smallest_set_with_enough_mass() -> None:
    probs = torch.tensor([[0.05, 0.5, 0.3, 0.15], [0.25, 0.25, 0.25, 0.25]])
    assert nucleus_mask(probs, 0.5).tolist() == [[False, True, False, False], [True, True, False, False]]
    assert nucleus_mask(probs, 0.8).tolist() == [[False, True, True, False], [True, True, True, True]]
    assert nucleus_mask(probs, 0.81).tolist()[0] == [False, True, True, True]
    assert nucleus_mask(probs, 1.0).all()
    u = counter_uniform(np.zeros(2000, np.uint64), np.arange(2000), np.zeros(2000))
    draws = sample_with_uniform(probs[:1].log().expand(2000, 4), 1.0, 0.8, u)
    assert set(draws.tolist()) == {1, 2}
    assert abs((draws == 1).mean() - 0.5 / 0.8) < 0.04


def test_probabilities_are_computed_once_and_drawn_from_alike() -> None:
    """The guard draws from :func:`token_probs` it shares with its checks: the same tokens as the logits."""
    logits = torch.randn(64, 384, generator=torch.Generator().manual_seed(1)) * 3
    u = counter_uniform(np.full(64, 7, np.uint64), np.arange(64), np.zeros(64))
    probs = token_probs(logits, 0.75)
    assert probs.dtype == torch.float64 and torch.allclose(probs.sum(-1), torch.ones(64, dtype=torch.float64))
    for top_p in (1.0, 0.9):
        drawn = sample_from_probs(probs, top_p, u)
        assert np.array_equal(drawn, sample_with_uniform(logits, 0.75, top_p, u))
    assert len(set(drawn.tolist())) > 20  # draws, not one argmax
    as_float64 = logits.double()
    token_probs(as_float64, 0.75)
    assert torch.equal(as_float64, logits.double())  # the caller's logits are left as they were
    with pytest.raises(ValueError, match="temperature must be > 0 for probabilities, got 0"):
        token_probs(logits, 0.0)


@pytest.mark.parametrize("variant", ["trajeglish", "no-intra"])
def test_greedy_rollout_is_a_fixed_point_of_the_teacher_forced_model(
    variant: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With temperature 0 every token the engine samples (through prime + decode_at) is the argmax of the
    full forward pass over its window given the whole result; replayed agents keep their log tokens."""
    ckpt = tiny_checkpoint(variant)
    model = ckpt.model
    sc = straight_road_scene(num_agents=5, steps=30)
    controlled = np.array([True, False, True, True, False])
    scenes = record_encoded(monkeypatch, model)
    config = SamplingConfig(temperature=0.0, prime_steps=3, guard=False)  # the model's own argmax
    horizon = config.every(model.cfg.steps)  # one window: it is never rebuilt
    engine = RolloutEngine(ckpt, sc, 2, horizon, controlled, config=config)
    engine.run()
    assert len(scenes) == 1  # both rows encoded in one block, once
    w, a = engine.windows[0], model.cfg.max_agents
    s0, t0 = int(w.start[0]), sc.current_index
    assert t0 - s0 == 3 and (engine.tokens[1] == engine.tokens[0]).all()  # greedy: both rows alike
    slots = w.slots[0]
    steps = np.arange(s0, s0 + model.cfg.steps)
    inputs = np.full((a, len(steps)), -1)
    inside = steps < engine.T - 1
    inputs[:, inside] = np.where(slots[:, None] >= 0, engine.tokens[0][slots][:, steps[inside]], -1)
    with torch.no_grad():
        logits = model(scenes[0].rows(slice(0, 1)), torch.from_numpy(inputs)[None])[0]  # [T,A,V]
    greedy = logits.argmax(-1).numpy()  # [T,A]
    for j, agent in enumerate(slots):
        if agent < 0:
            continue
        decided = engine.tokens[0, agent, t0 : t0 + horizon]
        if controlled[agent]:
            assert np.array_equal(decided, greedy[t0 - s0 : t0 - s0 + horizon, j])
        else:
            assert np.array_equal(engine.tokens[:, agent], np.stack([engine.tokens[0, agent]] * 2))
    other = RolloutEngine(
        ckpt, sc, 1, horizon, controlled, config=SamplingConfig(prime_steps=3, seed=4, guard=False)
    )
    other.run()
    assert np.array_equal(other.tokens[0, ~controlled], engine.tokens[0, ~controlled])  # replay: the log
    assert not np.array_equal(other.tokens[0, controlled], engine.tokens[0, controlled])


def test_the_second_number_is_uniform_reproducible_and_unrelated_to_the_first() -> None:
    """``second_uniform`` (the guard's redraw number): the same numbers for the same first ones, in [0, 1),
    uniform (mean, deciles) and uncorrelated with the first, over a million counter numbers."""
    from trajeglish_env.sampler.sampling import counter_uniform, second_uniform

    first = counter_uniform(np.full(1_000_000, 11), np.arange(1_000_000) // 50, np.arange(1_000_000) % 50)
    second = second_uniform(first)
    assert np.array_equal(second, second_uniform(first.copy()))
    assert second.min() >= 0.0 and second.max() < 1.0
    assert abs(second.mean() - 0.5) < 0.002
    assert np.abs(np.histogram(second, bins=10, range=(0, 1))[0] / 1e6 - 0.1).max() < 0.002
    assert abs(np.corrcoef(first, second)[0, 1]) < 0.005


def test_draft_draws_are_the_float64_draws_but_at_float32_rounding() -> None:
    """Drafts (:func:`draft_draws`, float32 in place) draw what the exact draw does wherever the number is
    not within float32 rounding of a CDF boundary; greedy and nucleus drafts are the exact draws."""
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(4000, 384, generator=g) * 3
    u = counter_uniform(np.full(4000, 11, np.uint64), np.arange(4000), np.zeros(4000))
    exact = sample_with_uniform(logits, 0.75, 1.0, u)
    scratch = logits.numpy().copy()
    drafts = draft_draws(scratch, 0.75, 1.0, u)
    assert not np.array_equal(scratch, logits.numpy())  # drawn in place
    cdf = token_probs(logits, 0.75).cumsum(-1).numpy()
    gap = np.abs(cdf - u[:, None]).min(axis=1)  # how close each number lies to a boundary
    assert np.array_equal(drafts[gap > 1e-5], exact[gap > 1e-5])
    assert (drafts == exact).mean() > 0.999 and len(set(drafts.tolist())) > 200
    for temperature, top_p in ((0.0, 1.0), (0.75, 0.9)):
        drawn = draft_draws(logits.numpy().copy(), temperature, top_p, u)
        assert np.array_equal(drawn, sample_with_uniform(logits, temperature, top_p, u))
    with pytest.raises(ValueError, match="temperature must be >= 0"):
        draft_draws(logits.numpy().copy(), -1.0, 1.0, u)
