"""Sampling with temperature/nucleus and cached decoding with forced tokens."""

from __future__ import annotations

import pytest
import torch
from test_model import random_scene

from trajeglish_env.model import TrajeglishModel, Variant, preset
from trajeglish_env.sampling import decode_tokens, nucleus_mask, sample_logits


def test_temperature_zero_is_argmax_and_small_temperature_approaches_it() -> None:
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(50, 7, generator=g)
    assert torch.equal(sample_logits(logits, 0.0), logits.argmax(-1))
    cold = sample_logits(logits, 1e-4, generator=torch.Generator().manual_seed(1))
    assert torch.equal(cold, logits.argmax(-1))
    with pytest.raises(ValueError, match="temperature must be >= 0"):
        sample_logits(logits, -1.0)


def test_nucleus_keeps_the_smallest_set_with_enough_mass() -> None:
    probs = torch.tensor([[0.05, 0.5, 0.3, 0.15], [0.25, 0.25, 0.25, 0.25]])
    assert nucleus_mask(probs, 0.5).tolist() == [[False, True, False, False], [True, True, False, False]]
    assert nucleus_mask(probs, 0.8).tolist() == [[False, True, True, False], [True, True, True, True]]
    assert nucleus_mask(probs, 0.81).tolist()[0] == [False, True, True, True]
    assert nucleus_mask(probs, 1.0).all()
    logits = probs.log()
    draws = sample_logits(logits.expand(2000, 2, 4), 1.0, 0.8, torch.Generator().manual_seed(0))
    assert set(draws[:, 0].tolist()) == {1, 2}
    assert abs((draws[:, 0] == 1).float().mean().item() - 0.5 / 0.8) < 0.04


@pytest.mark.parametrize("variant", [Variant.TRAJEGLISH, Variant.NO_INTRA])
def test_forced_tokens_stay_and_greedy_decoding_is_a_fixed_point(variant: Variant) -> None:
    torch.manual_seed(0)
    cfg = preset("tiny", variant=variant)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_scene(cfg, b=2, padded=1)
    sample = torch.zeros_like(tokens, dtype=torch.bool)
    sample[:, 1:3] = True  # the model controls agents 1 and 2; the others are forced
    out = decode_tokens(model, scene, tokens, sample, temperature=0.0)
    assert torch.equal(out[~sample], tokens[~sample])
    assert (out[:, -1] == -1).all()  # padding is never sampled
    assert ((out[sample] >= 0) & (out[sample] < cfg.vocab_size)).all()
    # greedy: each sampled token is the argmax of the teacher-forced logits given the whole result
    logits = model(scene, out).permute(0, 2, 1, 3)  # [B,A,T,V]
    assert torch.equal(out[sample], logits.argmax(-1)[sample])
    # same generator seed, same sample; another seed, another sample
    a = decode_tokens(model, scene, tokens, sample, 1.0, 1.0, torch.Generator().manual_seed(5))
    b = decode_tokens(model, scene, tokens, sample, 1.0, 1.0, torch.Generator().manual_seed(5))
    c = decode_tokens(model, scene, tokens, sample, 1.0, 1.0, torch.Generator().manual_seed(6))
    assert torch.equal(a, b) and not torch.equal(a, c)
