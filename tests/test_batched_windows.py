"""Training windows tokenized a batch at a time (``TokenizedWindows.__getitems__``, what each DataLoader
worker calls for its batch): every window, noisy input tokens included, is the one tokenizing it alone gives,
and the fast template search behind noisy tokens is the brute-force one."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import load_bundle

from trajeglish_env.checkpoint import load_pretrained
from trajeglish_env.tokenizer import NoiseConfig, TokenizeError, tokenize
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.nearest import templates_within
from trajeglish_env.training.dataset import make_window
from trajeglish_env.training.train import window_config
from trajeglish_env.training.training_data import TokenizedWindows


def _alone(ds: TokenizedWindows, g: int) -> dict[str, np.ndarray]:
    """Window ``g`` cut and tokenized by itself, with one Generator (no batching anywhere)."""
    epoch, scene = ds.order(g)
    rng = np.random.default_rng([ds.seed, epoch, scene])
    w = make_window(ds.scenes[scene], ds.window, rng, scene_index=scene)
    tok = tokenize(
        ds.vocabulary,
        w["agent_xyh"].astype(np.float64),
        w["agent_valid"] & w["agent_mask"][:, None],
        w["agent_size"].astype(np.float64),
        w["agent_kind"],
        noise=ds.noise,
        rng=rng,
    )
    return {**w, "tokens": tok.tokens, "input_tokens": tok.input_tokens}


def test_a_batch_of_windows_is_each_window_tokenized_alone() -> None:
    ckpt = load_pretrained()
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]  # highway-env and SUMO: three agent classes
    ds = TokenizedWindows(scenes, window_config(ckpt.config), ckpt.vocabulary, NoiseConfig(), seed=11)
    batch = ds.__getitems__(range(40, 64))
    noisy = 0
    for g, got in zip(range(40, 64), batch, strict=True):
        want = _alone(ds, g)
        assert sorted(got) == sorted(want)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=f"window {g}, field {key}")
        noisy += int((got["input_tokens"] != got["tokens"]).sum())
    kinds = {int(k) for w in batch for k in w["agent_kind"][w["agent_mask"]]}
    assert kinds == {0, 1, 2} and noisy > 100  # every class, and the noise draws matter
    assert (ds.collated(40, 64)["input_tokens"].numpy() == np.stack([w["input_tokens"] for w in batch])).all()


def test_templates_within_is_every_template_near_the_nearest_in_order() -> None:
    vocab = load_pretrained().vocabulary
    rng = np.random.default_rng(3)
    margin = NoiseConfig().margin(vocab.size)
    for k in range(vocab.num_kinds):
        table = vocab.search_tables[k]
        local = table.templates[rng.integers(0, table.size, 300)] + rng.normal(0, 0.04, (300, 3)) * [
            1,
            1,
            0.05,
        ]
        size = np.stack([rng.uniform(0.5, 6, 300), rng.uniform(0.5, 2.5, 300)], 1)
        r, c, d = templates_within(table, local, size, margin, chunk=128)
        full = corner_distance(table.templates[None], local[:, None], size[:, None])  # [300, V]
        want_r, want_c = np.nonzero(full <= full.min(1, keepdims=True) + margin)
        want_d = full[want_r, want_c]
        order = np.lexsort((want_c, want_d, want_r))
        np.testing.assert_array_equal(r, want_r[order])
        np.testing.assert_array_equal(c, want_c[order])
        np.testing.assert_allclose(d, want_d[order], rtol=0, atol=1e-12)
        assert len(r) > 3 * len(local)  # several candidates a row: the order within rows is tested


def test_per_scene_generators_must_match_the_scenes() -> None:
    vocab = load_pretrained().vocabulary
    xyh = np.zeros((2, 3, 4, 3))
    xyh[..., 0] = np.arange(4) * 0.5
    args = (vocab, xyh, np.ones((2, 3, 4), bool), np.ones((2, 3, 2)), np.zeros((2, 3), np.int64))
    gens = [np.random.default_rng(i) for i in range(3)]
    with pytest.raises(TokenizeError, match="one Generator per scene needs xyh \\[S, N, T, 3\\] with S = 3"):
        tokenize(*args, noise=NoiseConfig(), rng=gens)
    with pytest.raises(TokenizeError, match="rng: noisy tokenization needs a numpy.random.Generator"):
        tokenize(*args, noise=NoiseConfig(), rng=[1, 2])  # type: ignore[list-item]
    one = tokenize(*args, noise=NoiseConfig(), rng=gens[:2])
    assert one.input_tokens.shape == (2, 3, 3)
