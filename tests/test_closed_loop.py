"""CAT-K closed-loop training windows: the rollout follows the model's own decoding, its tokens are the
model's top-k, and the targets lead back to the log."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from helpers import grid_vocabulary, small_scenes, tiny_config

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.checkpoint_reading import drawn_base
from trajeglish_env.geometry import to_global
from trajeglish_env.model.network import SceneInputs
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.tokenize import render
from trajeglish_env.training.closed_loop import (
    ClosedLoopConfig,
    closed_loop_batch,
    closed_loop_rollout,
    recovery_aims,
    recovery_targets,
)
from trajeglish_env.training.dataset import collate_windows
from trajeglish_env.training.train import TrainConfig, train, window_config
from trajeglish_env.training.training_data import TokenizedWindows


@pytest.fixture(scope="module")
def shipped_batch():
    ckpt = drawn_base(load_pretrained())  # the model a run from the shipped one trains: it draws all it reads
    ds = TokenizedWindows(small_scenes(), window_config(ckpt.config), ckpt.vocabulary, None, seed=3)
    return ckpt, collate_windows([ds[g] for g in range(3)])


def test_all_tokens_allowed_reproduces_the_argmin_tokenization(shipped_batch) -> None:
    ckpt, batch = shipped_batch
    every = ClosedLoopConfig(top_k=ckpt.vocabulary.size, recovery=1.0, along_recovery=1.0)
    out = closed_loop_batch(ckpt.model, batch, ckpt.vocabulary, every)
    observed = batch["tokens"] >= 0
    assert int(observed.sum()) > 150
    b = len(batch["tokens"])
    for name, value in batch.items():  # the teacher-forced windows come first, unchanged
        assert torch.equal(out[name][:b], value)
    assert torch.equal(out["agent_xyh"][b:], batch["agent_xyh"])
    assert torch.equal(out["input_tokens"][b:], batch["tokens"])  # the nearest template of all: the argmin
    assert torch.equal(out["tokens"][b:], batch["tokens"])  # all the way back: the log's own tokens
    alone = closed_loop_batch(ckpt.model, batch, ckpt.vocabulary, replace(every, teacher_forced=False))
    assert torch.equal(alone["tokens"], out["tokens"][b:])


def test_rollout_takes_the_models_top_k_in_its_decoding_order(shipped_batch) -> None:
    ckpt, batch = shipped_batch
    model, vocab, k = ckpt.model, ckpt.vocabulary, 3
    model.train()
    tokens, states = closed_loop_rollout(model, batch, vocab, k)
    assert model.training  # the rollout runs in eval mode and restores the mode it found
    model.eval()
    moving = tokens >= 0
    assert torch.equal(torch.from_numpy(moving), batch["tokens"] >= 0)
    # teacher forcing the rolled-out tokens gives the logits the rollout chose from (the cache equals the
    # full forward): every chosen token ranks among the k most likely
    with torch.no_grad():
        logits = model(SceneInputs.from_batch(batch), torch.from_numpy(tokens))  # [B,T,A,V]
    chosen = torch.from_numpy(tokens).transpose(1, 2)  # [B,T,A]
    picked = logits.gather(-1, chosen.clamp(min=0)[..., None])
    rank = (logits > picked).sum(-1)
    assert int(rank[chosen >= 0].max()) < k
    # the states are those the tokens render from the window's anchors; they drift from the log
    logged = batch["agent_xyh"].double().numpy()
    valid = (batch["agent_valid"] & batch["agent_mask"][..., None]).numpy()
    anchored = valid.copy()
    anchored[..., 1:] &= ~valid[..., :-1]
    rendered, ok = render(vocab, tokens, batch["agent_kind"].numpy(), anchor_xyh=logged, anchored=anchored)
    assert np.array_equal(ok, valid)
    np.testing.assert_allclose(rendered[ok], states[ok], atol=1e-9)
    drift = np.linalg.norm(states[..., -1, :2] - logged[..., -1, :2], axis=-1)[valid[..., -1]]
    assert drift.mean() > 0.02  # top-3 of the model is not the log


@pytest.mark.parametrize("recovery,along", [(1.0, 1.0), (0.2, 0.0), (0.5, 0.2)])
def test_recovery_targets_close_the_asked_share_of_the_offset(recovery: float, along: float) -> None:
    steps = 4
    logged = np.zeros((1, 3, steps, 3))
    logged[..., 0] = np.arange(steps) * 1.0  # 10 m/s along x
    logged[0, 2, :, 2] = 0.3  # agent 2's log heads 0.3 rad left of x (and still moves along x)
    states = logged.copy()
    states[0, 0, :, 0] -= 0.5  # agent 0 is 0.5 m behind its log
    states[0, 1, :, 1] = 3.0  # agent 1 is 3 m to its side: beyond max_drift
    states[0, 2, :, 1] += 0.2  # agent 2 is 0.2 m to the left of its log
    cfg = ClosedLoopConfig(top_k=1, recovery=recovery, along_recovery=along, max_drift=2.0)
    aim = recovery_aims(states, logged, cfg)  # [1,3,T,3]
    np.testing.assert_allclose(aim[0, 0, :, 0], logged[0, 0, 1:, 0] - 0.5 * (1 - along), atol=1e-12)
    np.testing.assert_allclose(aim[0, 0, :, 1:], 0.0, atol=1e-12)
    # sideways in the log's frame: 0.2 m left of x is 0.2 cos(0.3) left and 0.2 sin(0.3) ahead of the log
    c, s = np.cos(0.3), np.sin(0.3)
    along_part, side = 0.2 * s * (1 - along), 0.2 * c * (1 - recovery)
    np.testing.assert_allclose(aim[0, 2, :, 0], logged[0, 2, 1:, 0] + along_part * c - side * s, atol=1e-12)
    np.testing.assert_allclose(aim[0, 2, :, 1], along_part * s + side * c, atol=1e-12)
    np.testing.assert_allclose(aim[0, 2, :, 2], 0.3, atol=1e-12)

    vocab = load_pretrained().vocabulary
    moving = np.ones((1, 3, steps - 1), dtype=bool)
    moving[0, 0, 1] = False
    size = np.broadcast_to(np.array([4.5, 2.0]), (1, 3, 2))
    kind = np.zeros((1, 3), dtype=np.int64)
    targets = recovery_targets(vocab, states, logged, moving, size, kind, cfg)
    assert (targets[0, 1] == -1).all() and targets[0, 0, 1] == -1
    # each target is the template of all whose box from the rolled-out state lands nearest the aim
    for a, t in [(0, 0), (0, 2), (2, 0), (2, 1)]:
        every = to_global(states[0, a, t], vocab.templates[0])
        best = np.argmin(corner_distance(every, aim[0, a, t], size[0, a]))
        assert targets[0, a, t] == best


def test_closed_loop_config_rejects_bad_settings() -> None:
    with pytest.raises(ValueError, match="top_k"):
        ClosedLoopConfig(top_k=0)
    with pytest.raises(ValueError, match="recovery"):
        ClosedLoopConfig(recovery=1.5)
    with pytest.raises(ValueError, match="along_recovery"):
        ClosedLoopConfig(along_recovery=-0.1)
    with pytest.raises(ValueError, match="max_drift"):
        TrainConfig(closed_loop_top_k=3, closed_loop_max_drift=0.0)
    assert TrainConfig().closed_loop() is None


def test_closed_loop_training_resumes_exactly(tmp_path) -> None:
    save_scenarios(tmp_path / "s" / "a.scn.npz", small_scenes())
    base = dict(
        steps=4,
        batch_size=2,
        warmup_steps=1,
        val_every=100,
        log_every=1,
        checkpoint_every=2,
        num_workers=0,
        val_fraction=0.0,
        closed_loop_top_k=4,
    )
    cfg = TrainConfig(**base)
    vocab = grid_vocabulary()
    whole = train(tmp_path / "s", tmp_path / "a", tiny_config(), cfg, vocabulary=vocab, progress=False)
    assert np.isfinite(whole["train_loss"])
    run = dict(vocabulary=vocab, progress=False)
    train(tmp_path / "s", tmp_path / "b", tiny_config(), cfg, **run, time_limit=0.0)  # stops after step 1
    train(tmp_path / "s", tmp_path / "b", tiny_config(), cfg, **run, resume=True)
    a = load_checkpoint(tmp_path / "a" / "model.pt").model.state_dict()
    b = load_checkpoint(tmp_path / "b" / "model.pt").model.state_dict()
    assert all(torch.equal(a[name], b[name]) for name in a)
    assert load_checkpoint(tmp_path / "a" / "model.pt").training["train_config"]["closed_loop_top_k"] == 4
