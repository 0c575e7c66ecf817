"""Cached decoding is exact: a position's numbers do not depend on the call that decodes it -- its chunk, a
look-ahead into the next step, or the other rows of the batch (TrajeglishModel._decode: at least
MIN_QUERIES queries, keys up to the end of the step after the chunk's first position)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from helpers import womd_tfrecord
from test_model import random_scene

from trajeglish_env.model import TrajeglishModel, preset
from trajeglish_env.model.layers import linear_compute
from trajeglish_env.model.masks import teacher_inputs


def test_a_position_decodes_to_the_same_numbers_in_any_chunk_and_batch() -> None:
    """Rows decode step 2 of a primed window (bfloat16 caches and products, as the engines decode) in
    different chunkings -- one position at a time, chunks of 2-3 from odd slots, the whole step with a
    look-ahead into step 3 -- beside rows chunked otherwise; every position's outputs and stored keys are
    the ones decoding it alone, one position at a time, gives, bit for bit."""
    torch.manual_seed(5)
    # the shipped model's widths (24 agent slots, 128 channels in 4 heads), 2 layers, 5 steps
    cfg = replace(preset("tiny"), d_model=128, num_heads=4, max_agents=24, steps=5)
    model = TrajeglishModel(cfg).eval()
    b, a = 4, cfg.max_agents
    scene, tokens = random_scene(cfg, b=b, padded=1, seed=6)
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(b, -1)
    carried, own = teacher_inputs(cfg.variant, ids, a)
    prefix = 2 * a
    chunkings = {
        "one at a time": [[1] * a] * b,
        "mixed": [[2, 3, a - 5], [a], [1, a - 1], [3, 3, a - 6]],
        "look-ahead": [[2 * a], [a - 1, a + 1], [2 * a], [1, 2 * a - 1]],
    }

    def decode(plan: list[list[int]]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        cache = model.empty_cache(b, torch.bfloat16)
        with torch.no_grad(), linear_compute(torch.bfloat16):
            agents = model.encode_into(cache, scene)
            model.prime(cache, agents, carried[:, :prefix], own[:, :prefix])
            out = torch.zeros(b, 2 * a, cfg.d_model)
            done = np.zeros(b, np.int64)
            for call in range(max(len(p) for p in plan)):
                count = np.array([p[call] if call < len(p) else 0 for p in plan])
                start = prefix + done
                n = int(count.max())
                cols = np.minimum(done[:, None] + np.arange(n), 2 * a - 1)
                rows = np.arange(b)[:, None]
                inputs = carried[:, prefix:][rows, cols], own[:, prefix:][rows, cols]
                hidden = model.decode_at(cache, agents, *inputs, start, count)
                for r in range(b):
                    out[r, done[r] : done[r] + count[r]] = hidden[r, : count[r]]
                done += count
        return out, [k[:, :, prefix : prefix + 2 * a].clone() for k in cache.self_k]

    ref_out, ref_keys = decode([[1] * (2 * a)] * b)
    for name, plan in chunkings.items():
        full = [p + [1] * (2 * a - sum(p)) for p in plan]  # every row runs to the end of step 3
        out, keys = decode(full)
        assert torch.equal(out, ref_out), name
        for got, want in zip(keys, ref_keys, strict=True):
            assert torch.equal(got, want), name


def test_parallel_decoding_of_the_shipped_model_is_sequential_and_batch_free_on_womd() -> None:
    """The shipped model on the shared WOMD scene (several contexts), bfloat16 caches and products: parallel
    decoding (drafts, look-ahead in small calls) draws the tokens sequential decoding draws, and a row's
    rollout is the same in a batch of three as alone (landed before step blocks: neither held; both drew
    other tokens within a few steps)."""
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.sampler import SamplingConfig
    from trajeglish_env.sampler.engine import BatchEngine
    from trajeglish_env.sampler.rows import RowSpec
    from trajeglish_env.sources.womd import read_womd

    sc = next(read_womd(womd_tfrecord()))
    live = sc.valid[:, sc.current_index]
    ckpt = load_pretrained()
    out = {}
    for mode, rows in (("sequential", 2), ("parallel", 2), ("alone", 1)):
        intra = "sequential" if mode == "sequential" else "parallel"
        config = SamplingConfig(intra_step=intra, compute_dtype="bfloat16")
        eng = BatchEngine(ckpt, rows, config)
        seeds = [21, 22][:rows] if mode != "alone" else [22]
        eng.start_rows(list(range(rows)), RowSpec(sc, 8, live), seeds)
        eng.run()
        out[mode] = eng.tokens.copy()
    np.testing.assert_array_equal(out["parallel"], out["sequential"])
    np.testing.assert_array_equal(out["alone"][0], out["parallel"][1])


def test_attention_rounds_alike_from_min_queries_queries_on() -> None:
    """What MIN_QUERIES rests on (this PyTorch's CPU kernels): a query's attention result is the same, bit
    for bit, in a call of MIN_QUERIES or more queries, from any slot, masked or not, float32 or bfloat16."""
    import torch.nn.functional as F

    from trajeglish_env.model.layers import MIN_QUERIES

    g = torch.Generator().manual_seed(1)
    for dtype in (torch.float32, torch.bfloat16):
        for keys in (56, 168, 300):
            q, k, v = (torch.randn(2, 4, n, 32, generator=g).to(dtype) for n in (24, keys, keys))
            mask = torch.zeros(2, 1, 24, keys, dtype=dtype)
            for i in range(24):
                mask[..., i, keys - 24 + i + 1 :] = float("-inf")
            for m in (None, mask):
                full = F.scaled_dot_product_attention(q, k, v, attn_mask=m)
                for first, stop in ((0, MIN_QUERIES), (3, 9), (20, 24), (5, 23)):
                    part = None if m is None else m[:, :, first:stop]
                    got = F.scaled_dot_product_attention(q[:, :, first:stop], k, v, attn_mask=part)
                    assert torch.equal(got, full[:, :, first:stop]), (dtype, keys, first, stop)
