"""A training step's cost without another function: the head at the targets alone against the full
logits, the causal attention of training against the explicit mask, and the arithmetic
(training/precision.py: bfloat16 autocast on CPU, products in bfloat16 and attention in float32, against
float32)."""

from __future__ import annotations

import pytest
import torch
from helpers import grid_vocabulary, random_scene_inputs, straight_road_scene, tiny_config

import trajeglish_env.model.layers as layers
import trajeglish_env.training.precision as precision
from trajeglish_env.checkpoint import load_checkpoint
from trajeglish_env.model import TrajeglishModel, preset
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.precision import step_autocast, step_dtype
from trajeglish_env.training.train import TrainConfig, train

CPU, CUDA = torch.device("cpu"), torch.device("cuda")


def test_the_choices_and_the_dtype_each_gives(monkeypatch) -> None:
    with pytest.raises(
        ValueError, match=r"precision must be one of \('auto', 'float32', 'bfloat16'\), got 'half'"
    ):
        TrainConfig(precision="half")
    assert step_dtype("float32", CPU, 128) == torch.float32
    assert step_dtype("bfloat16", CPU, 32) == torch.bfloat16
    for native, auto in ((True, torch.bfloat16), (False, torch.float32)):
        monkeypatch.setattr(precision, "native_bfloat16", lambda native=native: native)
        assert step_dtype("auto", CPU, 128) == step_dtype("auto", CPU, 64) == auto
        assert step_dtype("auto", CPU, 32) == torch.float32  # too narrow: bfloat16's casts cost more
        assert step_dtype("float32", CUDA, 32) == torch.bfloat16  # CUDA always autocasts
    assert not torch.is_autocast_enabled("cpu")
    with step_autocast("bfloat16", CPU, 32):
        assert torch.is_autocast_enabled("cpu")
    with step_autocast("float32", CPU, 128):
        assert not torch.is_autocast_enabled("cpu")


def _inputs(cfg, seed: int = 0) -> tuple:
    g = torch.Generator().manual_seed(seed)
    scene = random_scene_inputs(cfg, g)
    tokens = torch.randint(0, cfg.vocab_size, (1, cfg.max_agents, cfg.steps), generator=g)
    tokens[0, -1, :3] = -1  # some unobserved inputs
    return scene, tokens


@pytest.mark.parametrize("drawn", [None, 40])
@pytest.mark.parametrize("weighted", [False, True])
def test_the_training_head_at_the_targets_alone_gives_the_full_logits_loss_and_gradients(
    drawn, weighted
) -> None:
    """With gradients on, ``loss`` multiplies the head only at positions with a target, by their class's
    slice; its loss and every gradient are those of the full logits (``loss_of_logits(forward)``) on a
    window with three classes, empty slots, unobserved targets and (``drawn``) a model that reads more
    tokens than it draws."""
    torch.manual_seed(0)
    extra = {} if drawn is None else {"drawn_size": drawn, "token_bias": True}
    model = TrajeglishModel(preset("tiny", vocab_size=grid_vocabulary().size, **extra)).eval()
    cfg = model.cfg
    if drawn is not None:  # each read token counts as a drawn one (a reading extension's copies)
        model.token_source.copy_(torch.arange(cfg.vocab_size).remainder(drawn).expand(3, -1))
        torch.nn.init.normal_(model.token_bias)
    scene, tokens = _inputs(cfg, seed=2)
    g = torch.Generator().manual_seed(3)
    scene.agent_kind[:] = torch.randint(0, 3, scene.agent_kind.shape, generator=g)
    scene.agent_mask[0, -2:] = False  # two empty slots
    targets = tokens.clone()
    targets[0, 1, 2:5] = -1
    weights = 1 + torch.rand(targets.shape, generator=g) if weighted else None

    def run(full: bool) -> tuple[torch.Tensor, float, list[torch.Tensor]]:
        model.zero_grad(set_to_none=True)
        if full:
            mean, n = model.loss_of_logits(model.forward(scene, tokens), scene, targets, weights)
        else:
            mean, n = model.loss(scene, tokens, targets, weights=weights)
        mean.backward()
        return mean.detach(), n, [p.grad.clone() for p in model.parameters() if p.grad is not None]

    (fast, n_fast, g_fast), (full, n_full, g_full) = run(False), run(True)
    kept = int(((targets >= 0) & scene.agent_mask[:, :, None]).sum())
    assert n_fast == pytest.approx(n_full) and (weighted or n_full == kept)
    torch.testing.assert_close(fast, full, rtol=1e-6, atol=1e-6)
    assert len(g_fast) == len(g_full)
    for a, b in zip(g_fast, g_full, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    with torch.no_grad():  # inference keeps the full logits' path
        assert float(model.loss(scene, tokens, targets, weights=weights)[0]) == pytest.approx(float(full))


def test_training_attention_under_the_causal_flag_equals_the_explicit_mask() -> None:
    """With gradients on, the trajeglish variant attends with SDPA's causal flag instead of the explicit
    mask that inference (and the cached decoding) uses: the same logits, to float32 rounding."""
    torch.manual_seed(0)
    model = TrajeglishModel(tiny_config()).eval()  # no dropout: the two passes are comparable
    scene, tokens = _inputs(model.cfg)
    with torch.no_grad():
        masked = model.forward(scene, tokens)
    causal = model.forward(scene, tokens)
    assert causal.requires_grad
    torch.testing.assert_close(causal.detach(), masked, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="causal=True is for training"), torch.no_grad():
        x = torch.zeros(1, 4, model.cfg.d_model)
        block = model.blocks[0].self_attn
        block.attend(x, *block.keys_values(x), None, causal=True)


def test_bfloat16_autocast_multiplies_in_bfloat16_attends_in_float32_and_follows_float32(monkeypatch) -> None:
    torch.manual_seed(0)
    cfg = preset("tiny", vocab_size=grid_vocabulary().size)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = _inputs(cfg, seed=1)
    targets = tokens.clone()

    def grads(name: str) -> tuple[torch.Tensor, list[torch.Tensor]]:
        model.zero_grad(set_to_none=True)
        with step_autocast(name, CPU, cfg.d_model):
            mean, _ = model.loss(scene, tokens, targets)
        mean.backward()
        return mean.detach(), [p.grad.clone() for p in model.parameters() if p.grad is not None]

    seen: list[torch.dtype] = []
    sdpa = layers.F.scaled_dot_product_attention

    def recording(q, *args, **kw):  # type: ignore[no-untyped-def]
        seen.append(q.dtype)
        return sdpa(q, *args, **kw)

    linear_out: list[torch.dtype] = []
    hook = model.blocks[0].ff[0].register_forward_hook(lambda m, i, o: linear_out.append(o.dtype))
    monkeypatch.setattr(layers.F, "scaled_dot_product_attention", recording)
    loss16, g16 = grads("bfloat16")
    assert set(seen) == {torch.float32} and linear_out == [torch.bfloat16]
    seen.clear(), linear_out.clear()
    loss32, g32 = grads("float32")
    hook.remove()
    assert set(seen) == {torch.float32} and linear_out == [torch.float32]
    assert abs(float(loss16) - float(loss32)) < 0.01 * float(loss32), (loss16, loss32)
    flat16, flat32 = torch.cat([g.flatten() for g in g16]), torch.cat([g.flatten() for g in g32])
    cosine = float(torch.nn.functional.cosine_similarity(flat16, flat32, dim=0))
    assert cosine > 0.999, cosine
    assert all(g.dtype == torch.float32 for g in g16)  # float32 weights, gradients and optimizer state


def test_a_run_records_its_precision_and_may_resume_in_another(tmp_path, monkeypatch) -> None:
    """Precision is arithmetic, not the schedule: a run stopped after its step-2 checkpoint goes on in
    another precision (as on another machine), and the checkpoint says which it ran in."""
    import trajeglish_env.training.train as train_module

    data = tmp_path / "scenes"
    data.mkdir()
    save_scenarios(
        data / "a.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(3)]
    )
    quick = dict(
        steps=4, batch_size=4, warmup_steps=1, val_every=100, log_every=1, checkpoint_every=2, num_workers=0
    )
    vocab, real_write = grid_vocabulary(), train_module.write_metrics

    def crash_at_step_3(path, history):  # type: ignore[no-untyped-def]
        if history[-1]["step"] == 3:
            raise KeyboardInterrupt
        real_write(path, history)

    monkeypatch.setattr(train_module, "write_metrics", crash_at_step_3)
    with pytest.raises(KeyboardInterrupt):
        train(
            data,
            tmp_path / "run",
            tiny_config(),
            TrainConfig(**quick, precision="bfloat16"),
            vocab,
            progress=False,
        )
    assert load_checkpoint(tmp_path / "run" / "last.pt").training["train_config"]["precision"] == "bfloat16"
    monkeypatch.setattr(train_module, "write_metrics", real_write)
    on = TrainConfig(**quick, precision="float32")
    result = train(data, tmp_path / "run", tiny_config(), on, vocab, resume=True, progress=False)
    assert result["resumed_from"] == 2 and result["steps"] == 4
    assert load_checkpoint(tmp_path / "run" / "model.pt").training["train_config"]["precision"] == "float32"


def test_the_step_time_script_times_real_windows(tmp_path, capsys, monkeypatch) -> None:
    import json
    import runpy
    import sys
    from pathlib import Path

    save_scenarios(
        tmp_path / "a.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(3)]
    )
    script = Path(__file__).parents[1] / "scripts" / "training_step_time.py"
    argv = [
        str(script),
        "--data",
        str(tmp_path),
        "--precision",
        "float32",
        "--steps",
        "1",
        "--batch-size",
        "2",
    ]
    monkeypatch.setattr(sys, "argv", argv)
    threads = torch.get_num_threads()
    try:
        runpy.run_path(str(script), run_name="__main__")
    finally:
        torch.set_num_threads(threads)  # the script takes one thread; the worker's other tests keep theirs
    out = json.loads(capsys.readouterr().out)
    assert out["dtype"] == "float32" and out["positions_a_step"] == 2 * 24 * 24
    assert 0 < out["targets_a_step"] <= 2 * 5 * 24 and out["seconds_a_step"] > 0
    parts = out["forward"] + out["backward"] + out["optimizer"]
    assert out["seconds_a_step"] == pytest.approx(parts, abs=0.003)
