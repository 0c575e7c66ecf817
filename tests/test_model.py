"""Model shapes, variant masks (by perturbing forbidden inputs) and KV-cache equivalence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from trajeglish_env.model import SceneInputs, TrajeglishModel, Variant, preset
from trajeglish_env.model.masks import START, teacher_inputs


def random_scene(cfg, b: int = 2, seed: int = 0, padded: int = 1) -> tuple[SceneInputs, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a, m, p = cfg.max_agents, cfg.max_polylines, cfg.points_per_polyline
    agent_mask = torch.ones(b, a, dtype=torch.bool)
    agent_mask[:, a - padded :] = False
    scene = SceneInputs(
        agent_xyh=torch.randn(b, a, 3, generator=g) * 10,
        agent_size=torch.rand(b, a, 2, generator=g) * 4 + 0.5,
        agent_kind=torch.randint(0, 3, (b, a), generator=g),
        agent_mask=agent_mask,
        map_points=torch.randn(b, m, p, 2, generator=g) * 30,
        map_point_mask=torch.rand(b, m, p, generator=g) > 0.2,
        map_kind=torch.randint(0, 20, (b, m), generator=g),
        map_mask=torch.rand(b, m, generator=g) > 0.3,
        map_signal=torch.randint(0, 4, (b, m), generator=g),
    )
    tokens = torch.randint(0, cfg.vocab_size, (b, a, cfg.steps), generator=g)
    tokens[:, a - padded :] = -1
    tokens[0, 1, 3] = -1  # an unobserved step
    return scene, tokens


def may_use(variant: Variant, target: tuple[int, int], token: tuple[int, int], agents: int) -> bool:
    """The specification: may the prediction for (step, agent) ``target`` depend on ``token``?"""
    (t, a), (s, j) = target, token
    if variant is Variant.TRAJEGLISH:
        return s * agents + j < t * agents + a  # earlier in the flattened, time-major order
    if variant is Variant.NO_INTRA:
        return s < t  # nothing of its own timestep
    return s < t and j == a  # marginal / no-map: only its own past


@pytest.mark.parametrize("variant", list(Variant))
def test_a_token_never_sees_what_its_variant_forbids(variant: Variant) -> None:
    torch.manual_seed(0)
    cfg = preset("tiny", variant=variant)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_scene(cfg)
    base = model(scene, tokens)
    assert base.shape == (2, cfg.steps, cfg.max_agents, cfg.vocab_size)
    real = cfg.max_agents - 1  # the last slot is padding
    used = torch.zeros(cfg.steps, real, dtype=torch.bool)  # targets that reacted to an allowed change
    for j in range(real):
        for s in range(cfg.steps):
            changed = tokens.clone()
            changed[:, j, s] = (changed[:, j, s] + 7) % cfg.vocab_size
            diff = (model(scene, changed) - base).abs().amax(dim=(0, 3))  # [T,A]
            for t in range(cfg.steps):
                for a in range(real):
                    if may_use(variant, (t, a), (s, j), cfg.max_agents):
                        used[t, a] |= bool(diff[t, a] > 1e-5)
                    else:
                        assert diff[t, a] < 1e-5, (
                            f"{variant.value}: target (t={t}, a={a}) saw token ({j}, {s})"
                        )
    assert used[1:].all()  # every target after the first step does use what it may


def test_no_map_variant_ignores_the_map() -> None:
    cfg = preset("tiny", variant=Variant.NO_MAP)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_scene(cfg)
    other = SceneInputs(
        **{**scene.__dict__, "map_points": scene.map_points * 3.0, "map_kind": scene.map_kind // 2}
    )
    torch.testing.assert_close(model(scene, tokens), model(other, tokens))
    full = TrajeglishModel(preset("tiny")).eval()
    assert (full(scene, tokens) - full(other, tokens)).abs().max() > 1e-3


@pytest.mark.parametrize("variant", list(Variant))
def test_cached_decoding_equals_full_forward(variant: Variant) -> None:
    torch.manual_seed(1)
    cfg = preset("tiny", variant=variant)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_scene(cfg, b=2, padded=2)
    full = model(scene, tokens)  # [B,T,A,V]
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(2, -1)
    carried, own = teacher_inputs(variant, ids, cfg.max_agents)
    assert (carried[:, 0] == START).all() and (own[:, : cfg.max_agents] == -1).all()
    a = cfg.max_agents
    # one position at a time (how trajeglish samples), and one timestep at a time (the other variants)
    chunk = 1 if variant is Variant.TRAJEGLISH else a
    cache = model.empty_cache(2, torch.float32)
    agents = model.encode_into(cache, scene)
    worst = 0.0
    for p in range(0, cfg.steps * a, chunk):
        start, count = np.full(2, p), np.full(2, chunk)
        hidden = model.decode_at(
            cache, agents, carried[:, p : p + chunk], own[:, p : p + chunk], start, count
        )
        t = p // a
        with torch.no_grad():
            logits = model.class_logits(hidden, scene.agent_kind[:, p % a : p % a + chunk])
        want = full[:, t, p % a : p % a + chunk]
        worst = max(worst, (logits - want).abs().max().item())
    assert worst <= 1e-4
    with pytest.raises(ValueError, match="must fit the cache"):
        model.decode_at(cache, agents, carried[:, :chunk], own[:, :chunk], start + chunk, count)


def test_primed_cache_equals_decoded_cache() -> None:
    """Priming stores exactly the keys/values that decoding the same positions stores."""
    cfg = preset("tiny")
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_scene(cfg, b=2, padded=2)
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(2, -1)
    carried, own = teacher_inputs(cfg.variant, ids, cfg.max_agents)
    n = 3 * cfg.max_agents
    primed, decoded = model.empty_cache(2, torch.float32), model.empty_cache(2, torch.float32)
    agents = model.encode_into(primed, scene)
    model.encode_into(decoded, scene)
    model.prime(primed, agents, carried[:, :n], own[:, :n])
    model.decode_at(decoded, agents, carried[:, :n], own[:, :n], np.zeros(2, np.int64), np.full(2, n))
    for k in range(len(model.blocks)):
        assert torch.equal(primed.self_k[k], decoded.self_k[k])
        assert torch.equal(primed.self_v[k], decoded.self_v[k])
    assert primed.self_k[0][:, :, :n].abs().sum() > 0 and not primed.self_k[0][:, :, n:].any()


def test_loss_ignores_unobserved_and_padding() -> None:
    cfg = preset("tiny")
    model = TrajeglishModel(cfg)
    scene, tokens = random_scene(cfg, padded=2)
    loss, n = model.loss(scene, tokens, tokens)
    assert n == 2 * (cfg.max_agents - 2) * cfg.steps - 1
    assert (
        abs(loss.item() - torch.log(torch.tensor(float(cfg.vocab_size))).item()) < 1.0
    )  # near uniform at init
    with pytest.raises(ValueError, match="at most 6 agents x 8 steps"):
        model(scene, torch.zeros(2, 6, 9, dtype=torch.long))


def test_padding_polylines_never_make_gradients_non_finite() -> None:
    """A polyline with no points (padding of a sparse map) pools to the fill value; with grown weights
    that overflowed the next layer and sent NaN gradients back through the discarded output (a small
    training run blew up at step 2,167). Its pool is now zeroed before it is used."""
    torch.manual_seed(0)
    cfg = preset("tiny")
    model = TrajeglishModel(cfg)
    with torch.no_grad():
        for p in model.encoder.polylines.second.parameters():
            p.mul_(50.0)  # weights a long run can reach
    scene, tokens = random_scene(cfg)
    scene.map_point_mask[:, -3:] = False  # three padding polylines
    loss, _ = model.loss(scene, tokens, tokens)
    loss.backward()
    bad = [
        name
        for name, p in model.named_parameters()
        if p.grad is not None and not torch.isfinite(p.grad).all()
    ]
    assert torch.isfinite(loss) and not bad, bad


def test_inference_encodes_polylines_block_by_block_exactly(monkeypatch: pytest.MonkeyPatch) -> None:
    """At inference the polylines with points are encoded in small blocks (activations stay in the CPU
    cache); the result is the whole-batch (training) computation, padding polylines included."""
    from trajeglish_env.model.encoder import PolylineEncoder

    torch.manual_seed(0)
    cfg = preset("tiny")
    encoder = TrajeglishModel(cfg).encoder.polylines
    scene, _ = random_scene(cfg, b=3)
    scene.map_point_mask[1, :5] = False  # five polylines without points
    args = (scene.map_points, scene.map_point_mask, scene.map_kind)
    with torch.enable_grad():
        whole = encoder(*args).detach()
    monkeypatch.setattr(PolylineEncoder, "INFERENCE_BLOCK", 7)  # 48 polylines: 7 blocks, the last short
    with torch.no_grad():
        blocks = encoder(*args)
    torch.testing.assert_close(blocks, whole, rtol=0, atol=1e-6)
    torch.testing.assert_close(blocks[1, :5], encoder.kind(scene.map_kind[1, :5]).detach(), rtol=0, atol=0)


def test_logits_of_known_classes_equal_the_full_head() -> None:
    """The engine multiplies only each class's slice of the tied head (or, up to JOINT_HEAD_ROWS rows of
    several classes, every class's drawn slice in one product): the same numbers as the full head, for a
    tiny model and the shipped one (which draws 384 of its 2,048 tokens per class)."""
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.model.network import JOINT_HEAD_ROWS

    torch.manual_seed(1)
    biased = TrajeglishModel(dataclasses.replace(preset("tiny"), token_bias=True)).eval()
    with torch.no_grad():
        biased.token_bias.normal_()  # type: ignore[union-attr]
    for model in (TrajeglishModel(preset("tiny")).eval(), biased, load_pretrained().model):
        for n in (1, 5, 40, JOINT_HEAD_ROWS, JOINT_HEAD_ROWS + 1, 130):
            hidden = torch.randn(n, model.cfg.d_model)
            for kind in (torch.randint(0, 3, (n,)), torch.zeros(n, dtype=torch.long)):
                with torch.no_grad():
                    want = model.class_logits(hidden, kind)
                    assert torch.equal(model.class_logits_by_kind(hidden, kind.numpy()), want)
    assert model.cfg.drawn < model.cfg.vocab_size and model._drawn_copy is not None


def test_idle_rows_are_left_out_of_a_decoding_call_and_untouched() -> None:
    """Rows with nothing to decode (count 0) are not computed: the busy rows' outputs and caches are the
    ones a call with every row busy gives, bit for bit, and the idle rows' caches stay as they were."""
    torch.manual_seed(2)
    cfg = preset("tiny")
    model = TrajeglishModel(cfg).eval()
    b, a = 4, cfg.max_agents
    scene, tokens = random_scene(cfg, b=b, padded=2)
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(b, -1)
    carried, own = teacher_inputs(cfg.variant, ids, a)
    prefix = 2 * a + 3
    caches = [model.empty_cache(b, torch.bfloat16) for _ in range(2)]
    agents = [model.encode_into(cache, scene) for cache in caches]
    for cache, emb in zip(caches, agents, strict=True):
        model.prime(cache, emb, carried[:, :prefix], own[:, :prefix])
    n = a  # rows 1 and 3 idle, rows 0 and 2 decode chunks of their own lengths from their own starts
    start, count = np.array([prefix, 0, prefix - 2, 0]), np.array([a - 2, 0, a, 0])
    window = [carried[r, s : s + n] for r, s in enumerate(start)]
    own_window = [own[r, s : s + n] for r, s in enumerate(start)]
    inputs = torch.stack(window), torch.stack(own_window)
    before = [k.clone() for k in caches[0].self_k]
    hidden = model.decode_at(caches[0], agents[0], *inputs, start, count)
    every = np.where(count > 0, count, 1)  # the reference: every row busy (idle ones redo position 0)
    ref = model.decode_at(caches[1], agents[1], *inputs, np.where(count > 0, start, 0), every)
    for r in (0, 2):
        assert torch.equal(hidden[r, : count[r]], ref[r, : count[r]])
        for k in range(len(model.blocks)):
            assert torch.equal(caches[0].self_k[k][r], caches[1].self_k[k][r])
    for r in (1, 3):
        assert not hidden[r].any()
        assert all(torch.equal(caches[0].self_k[k][r], before[k][r]) for k in range(len(model.blocks)))


def test_busy_rows_read_their_cache_rows_as_runs_of_views_with_the_gathered_numbers() -> None:
    """A partly busy call attends run by run over views of consecutive cache rows (no copy of the cache):
    rows 0, 2-3 and 5 of 6 (three runs, one of two rows) give, bit for bit, the outputs and caches of a
    call with every row busy, in bfloat16 caches and products as the engines decode."""
    from trajeglish_env.model.layers import Attention, linear_compute, row_runs

    assert row_runs(np.array([0, 2, 3, 5])) == ((0, 1, 0), (1, 3, 2), (3, 4, 5))
    assert row_runs(np.array([4, 5, 6])) == ((0, 3, 4),)
    torch.manual_seed(3)
    cfg = preset("tiny")
    model = TrajeglishModel(cfg).eval()
    b, a = 6, cfg.max_agents
    scene, tokens = random_scene(cfg, b=b, padded=2, seed=4)
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(b, -1)
    carried, own = teacher_inputs(cfg.variant, ids, a)
    prefix = a + 2
    caches = [model.empty_cache(b, torch.bfloat16) for _ in range(2)]
    with torch.no_grad(), linear_compute(torch.bfloat16):
        agents = [model.encode_into(cache, scene) for cache in caches]
        for cache, emb in zip(caches, agents, strict=True):
            model.prime(cache, emb, carried[:, :prefix], own[:, :prefix])
        busy = np.array([True, False, True, True, False, True])
        start, count = np.full(b, prefix), np.where(busy, a - 2, 0)
        inputs = carried[:, prefix : prefix + a - 2], own[:, prefix : prefix + a - 2]
        hidden = model.decode_at(caches[0], agents[0], *inputs, start, count)
        ref = model.decode_at(caches[1], agents[1], *inputs, start, np.full(b, a - 2))
        for r in np.flatnonzero(busy):
            assert torch.equal(hidden[r], ref[r])
            for k in range(len(model.blocks)):
                assert torch.equal(caches[0].self_k[k][r], caches[1].self_k[k][r])
        # the attention alone: runs of views against the gathered rows
        attn = Attention(cfg.d_model, cfg.num_heads).eval()
        k, v = caches[1].self_k[0], caches[1].self_v[0]
        rows = np.flatnonzero(busy)
        x = torch.randn(len(rows), 3, cfg.d_model)
        keys = prefix + 3
        mask = torch.rand(len(rows), 1, 3, keys) > 0.3
        mask[..., 0] = True
        got = attn.attend_runs(x, k, v, keys, mask, row_runs(rows))
        want = attn.attend(x, k[rows, :, :keys], v[rows, :, :keys], mask)
    assert torch.equal(got, want)
